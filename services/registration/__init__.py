"""Infrared-to-visible image registration by mutual information; see docs/registration.md."""
