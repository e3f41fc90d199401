"""The HDF5 asset: one file with the spring network, material, tables and provenance.

See docs/reference/asset-format.md for the schema. ``write_asset`` writes it (and an
XDMF sidecar for ParaView) atomically; ``read_asset`` reads it back and
refuses anything truncated, tampered with or of an unknown/newer schema;
``validate_asset`` lists every problem; ``update_asset_tables`` rewrites the
stiffness tables (and material) of an existing asset.

Modules: :mod:`.schema` (types, versions, units), :mod:`.hdf5` (typed groups,
text, content hashes, the sealed file header), :mod:`.material` (``/material``),
:mod:`.tables` (``/tables``), :mod:`.provenance`, :mod:`.xdmf` (the ParaView
sidecars), :mod:`.accuracy` (``/accuracy``: the fit's and the validation's errors) and
:mod:`.trust` (:class:`Accuracy`: how far to trust the asset, in words), :mod:`.write`,
:mod:`.read` and :mod:`.rewrite` (``record_validation``: ``esmm validate``'s figures into
the asset).
"""

from .accuracy import fit_record
from .provenance import Provenance, collect_provenance
from .read import Asset, read_asset, validate_asset
from .rewrite import record_validation, update_asset_tables
from .trust import Accuracy
from .write import write_asset

__all__ = ["Accuracy", "Asset", "Provenance", "collect_provenance", "fit_record", "read_asset",
           "record_validation", "update_asset_tables", "validate_asset", "write_asset"]
