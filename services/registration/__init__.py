"""Infrared-to-visible image registration by mutual information or normalised gradient fields.

See docs/registration.md.
"""
