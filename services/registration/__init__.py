"""Infrared-to-visible image registration by normalised gradient fields (the default) or mutual information.

See docs/registration.md.
"""
