"""The virtual rig: scenes, exact ray casting, and rendered camera frames with their ground truth (docs/simulator.md)."""
