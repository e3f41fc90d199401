"""Tensile-test files: reading (``read``) and the :class:`TensileTest` object."""

from .data import MODES, TensileTest

__all__ = ["MODES", "TensileTest"]
