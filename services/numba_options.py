"""Compilation options shared by the numba kernels."""

# Floating-point licences that keep NaN and infinity semantics (rejection tests and NaN markers rely on
# them) but let LLVM fuse multiply-adds, reassociate sums and use reciprocals, so that loops vectorise.
SAFE_FASTMATH = {"contract", "arcp", "reassoc"}
