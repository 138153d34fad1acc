"""Tessera's library: pure computation on numpy arrays plus the plumbing every service shares.

Nothing in this package starts a process or owns a socket's lifetime.
"""

__version__ = "0.1.0"
