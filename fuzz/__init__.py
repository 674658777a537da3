"""Fuzzing harnesses for the decoders (see README.md); the shared targets are in targets.py."""
