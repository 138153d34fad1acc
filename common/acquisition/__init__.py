"""Acquisition: flatbed scanning and photometric stereo (thesis chapter 3)."""
