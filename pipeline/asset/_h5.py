"""Small HDF5 helpers shared by the asset writer, reader and validator."""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any

import h5py
import numpy as np

from .schema import CHECKSUM_ATTR

TEXT = h5py.string_dtype(encoding="utf-8")


def put(group: h5py.Group, name: str, data, units: str, *, dtype=None, description: str = "") -> h5py.Dataset:
    """Create dataset *name* in *group* with a ``units`` attribute (and a description)."""
    arr = np.asarray(data, dtype=dtype) if dtype is not None else np.asarray(data)
    ds = group.create_dataset(name, data=arr)
    ds.attrs["units"] = units
    if description:
        ds.attrs["description"] = description
    return ds


def put_text(group: h5py.Group, name: str, text: str, *, description: str = "") -> h5py.Dataset:
    """Create a scalar UTF-8 text dataset (``units = "text"``)."""
    ds = group.create_dataset(name, data=str(text), dtype=TEXT)
    ds.attrs["units"] = "text"
    if description:
        ds.attrs["description"] = description
    return ds


def get_text(ds: h5py.Dataset) -> str:
    """Read a scalar text dataset as ``str``."""
    value = ds.asstr()[()] if ds.dtype.kind in "OS" else ds[()]
    if isinstance(value, bytes):
        return value.decode("utf-8")
    return str(value)


def typed_group(parent: h5py.Group, name: str, esmm_type: str, version: int) -> h5py.Group:
    """Create group *name* with its ``esmm_type`` and ``esmm_version`` attributes."""
    g = parent.create_group(name)
    g.attrs["esmm_type"] = esmm_type
    g.attrs["esmm_version"] = int(version)
    return g


def attr_str(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        return attr_str(value.item())
    return "" if value is None else str(value)


def attr_int(value, default: int = -1) -> int:
    try:
        return int(np.asarray(value).item())
    except (TypeError, ValueError):
        return default


# -- content hashes ----------------------------------------------------------------------------

def dataset_digest(ds: h5py.Dataset) -> str:
    """SHA-256 over dtype, shape and content (little-endian, C order) of a dataset."""
    h = hashlib.sha256()
    if ds.dtype.kind in "OS" and h5py.check_string_dtype(ds.dtype) is not None:
        data = ds.asstr()[()]
        flat = [data] if isinstance(data, str) else list(np.asarray(data, dtype=object).ravel())
        h.update(f"text|{ds.shape}|".encode())
        for s in flat:
            b = s.encode("utf-8")
            h.update(len(b).to_bytes(8, "little"))
            h.update(b)
        return h.hexdigest()
    arr = np.ascontiguousarray(ds[()])
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    h.update(f"{arr.dtype.str}|{arr.shape}|".encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def _jsonable(value) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()] if value.ndim else _jsonable(value.item())
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return value


def manifest(f: h5py.File) -> str:
    """SHA-256 of the canonical listing of every object's attributes (root checksum excluded)."""
    entries: list = []

    def visit(name: str, obj) -> None:
        attrs = {k: _jsonable(v) for k, v in obj.attrs.items() if not (name == "/" and k == CHECKSUM_ATTR)}
        kind = "dataset" if isinstance(obj, h5py.Dataset) else "group"
        entries.append(["/" + name if name != "/" else "/", kind, sorted(attrs.items())])

    visit("/", f)
    f.visititems(visit)
    entries.sort(key=lambda e: e[0])
    text = json.dumps(entries, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def seal(f: h5py.File) -> None:
    """Store each dataset's digest in its ``sha256`` attribute, then the root checksum."""
    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            obj.attrs["sha256"] = dataset_digest(obj)

    f.visititems(visit)
    f.attrs[CHECKSUM_ATTR] = manifest(f)


def to_json(obj) -> str:
    """JSON text of a report (dataclass, dict, numpy values), keys sorted."""
    import dataclasses

    def conv(o):
        if dataclasses.is_dataclass(o) and not isinstance(o, type):
            return {f.name: conv(getattr(o, f.name)) for f in dataclasses.fields(o)}
        if isinstance(o, dict):
            return {str(k): conv(v) for k, v in o.items()}
        if isinstance(o, (list, tuple, set)):
            return [conv(v) for v in o]
        if isinstance(o, np.ndarray):
            return conv(o.tolist())
        if isinstance(o, np.generic):
            return conv(o.item())
        if isinstance(o, float) and not math.isfinite(o):
            return None if math.isnan(o) else ("inf" if o > 0 else "-inf")
        if isinstance(o, (str, int, float, bool)) or o is None:
            return o
        return str(o)

    return json.dumps(conv(obj), sort_keys=True, indent=1)
