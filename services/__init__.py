"""Tessera's processes: each module is a short shell around ``common``."""
