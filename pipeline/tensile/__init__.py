"""Tensile-test files: reading (``read``) and the :class:`TensileTest` object."""

from .data import MODES, TensileTest
from .reader import NotATestError, read

__all__ = ["MODES", "NotATestError", "TensileTest", "read"]
