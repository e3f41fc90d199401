"""The asset schema: group types, versions and the unit of every dataset.

The authoritative description is docs/reference/asset-format.md; this module is its
machine-readable part. Every group carries the attributes ``esmm_type`` and
``esmm_version`` (an integer, bumped on any incompatible change); every
dataset carries ``units`` (an SI unit, ``"1"`` for dimensionless numbers,
``"index"`` for node indices, ``"text"`` for UTF-8 text) and ``sha256``.
"""

from __future__ import annotations

#: The root group.
ASSET_TYPE = "esmm_asset"
ASSET_VERSION = 1

#: Root attribute holding the SHA-256 of the canonical listing of every attribute and dataset hash.
CHECKSUM_ATTR = "esmm_checksum"

#: group path -> (esmm_type, version this esmm writes and reads, required?)
GROUPS: dict[str, tuple[str, int, bool]] = {
    "/mesh": ("mesh", 1, True),
    "/springs": ("springs", 1, True),
    "/nodes": ("nodes", 1, True),
    "/material": ("material", 1, False),
    "/material/effects": ("material_effects", 1, False),          # kept material effects (discover)
    "/material/effects/viscoelastic": ("viscoelastic_effect", 1, False),
    "/material/effects/mullins": ("mullins_effect", 1, False),
    "/material/effects/damage": ("damage_effect", 1, False),
    "/tables": ("stiffness_tables", 1, False),   # asset/tables.py
    "/volume": ("volume_term", 1, False),        # asset/volume.py: the network's volume elements
    "/quality": ("quality", 1, False),
    "/cleaning": ("cleaning", 1, False),
    "/accuracy": ("accuracy", 1, False),                 # asset/accuracy.py: how far to trust the asset
    "/accuracy/fit": ("fit_accuracy", 1, False),         # the material fit's error (prepare)
    "/accuracy/validation": ("validation_accuracy", 1, False),  # against a continuum (esmm validate)
    "/provenance": ("provenance", 1, True),
}

#: dataset path -> (units, numpy dtype kind(s) accepted, required?)
DATASETS: dict[str, tuple[str, str, bool]] = {
    "/mesh/points": ("m", "f", True),
    "/mesh/tets": ("index", "iu", False),          # absent for the skeleton structure
    "/mesh/quadratic_cells": ("index", "iu", False),  # a split mesh's parents as 10-node cells
    "/mesh/surface_faces": ("index", "iu", True),
    "/mesh/node_kind": ("1", "u", True),
    "/springs/pairs": ("index", "iu", True),
    "/springs/rest_length": ("m", "f", True),
    "/springs/volume": ("m3", "f", True),
    "/springs/volume_weight": ("m", "f", True),
    "/springs/cos2": ("1", "f", True),
    "/springs/fibre_frame": ("1", "f", True),
    "/springs/affine_elasticity": ("1", "f", True),
    "/nodes/mass": ("kg", "f", True),
    "/nodes/fixed": ("index", "iu", True),
    "/nodes/fixed_mask": ("1", "u", True),
    "/material/toml": ("text", "OS", True),
    "/material/effects/viscoelastic/g": ("1", "f", True),
    "/material/effects/viscoelastic/tau": ("s", "f", True),
    "/material/effects/mullins/r": ("1", "f", True),
    "/material/effects/mullins/m": ("Pa", "f", True),
    "/material/effects/mullins/beta": ("1", "f", True),
    "/material/effects/damage/onset": ("1", "f", True),
    "/material/effects/damage/scale": ("1", "f", True),
    "/material/effects/damage/shape": ("1", "f", True),
    "/material/effects/damage/floor": ("1", "f", False),
    "/volume/bulk_modulus": ("Pa", "f", True),
    "/volume/rest_volume": ("m3", "f", True),
    "/volume/shear_modulus": ("Pa", "f", False),
    "/quality/report": ("text", "OS", True),
    "/cleaning/report": ("text", "OS", True),
    "/accuracy/fit/record": ("text", "OS", True),
    "/accuracy/validation/record": ("text", "OS", True),
    "/provenance/config_toml": ("text", "OS", True),
    "/provenance/command_line": ("text", "OS", True),
    "/provenance/packages": ("text", "OS", True),
}

#: Units a dataset may have (anything else is refused by the validator).
KNOWN_UNITS = {"m", "m2", "m3", "kg", "kg/m3", "Pa", "N", "N/m", "s", "1", "index", "text"}
