"""Tensile-test files: reading (``read``) and the :class:`TensileTest` object."""

from .data import MODES, TensileTest
from .reader import read

__all__ = ["MODES", "TensileTest", "read"]
