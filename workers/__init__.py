"""Dramatiq workers: actors for calibrate, reconstruct, register, fuse and scan, and their middleware."""
