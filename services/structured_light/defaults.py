"""The decoder's options that reach the command line, each with its one default (a module without imports, so
that a command's ``--help`` can name them without loading the decoder)."""

CONSISTENCY = 0.25
"""Tolerance of the Gray code or coarser period against the unwrapped phase, as a fraction of the unwrapping
margin."""

MAX_INDIRECT = float("inf")
"""Largest inter-reflected to direct light ratio a pixel may show; infinite: no such rejection."""
