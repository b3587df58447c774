"""Cameras, rotations, splines and planes: pure math shared by every branch."""
