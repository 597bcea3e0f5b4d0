"""The paper's distributed hybrid feedback for pose synchronisation on SE(3)."""
__version__ = "0.1.0"
