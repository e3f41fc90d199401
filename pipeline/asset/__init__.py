"""The HDF5 asset: one file with the spring network, material, tables and provenance.

See docs/asset-format.md for the schema. ``write_asset`` writes it (and an
XDMF sidecar for ParaView) atomically; ``read_asset`` reads it back and
refuses anything truncated, tampered with or of an unknown/newer schema;
``validate_asset`` lists every problem.
"""

from .provenance import Provenance, collect_provenance
from .read import Asset, read_asset, validate_asset
from .write import write_asset

__all__ = ["Asset", "Provenance", "collect_provenance", "read_asset", "validate_asset", "write_asset"]
