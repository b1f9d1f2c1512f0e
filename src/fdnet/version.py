"""fdnet's version, on the ground floor so any module records it without importing the package's
public API (``fdnet.load``, which reaches a trained method)."""

__version__ = "0.1.0"
