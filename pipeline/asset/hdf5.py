"""HDF5 helpers of the asset: typed groups, text datasets, content hashes and the sealed file header.

Shared by the asset writer, reader, validator and rewriter; :func:`seal` is what every
writer that creates or edits an asset calls last (tests use it to make consistent edits).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
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
    """An integer attribute; *default* for anything that is not one (text, arrays, NaN, infinity)."""
    try:
        return int(np.asarray(value).item())
    except (TypeError, ValueError, OverflowError):
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


def seal_content(f: h5py.File) -> None:
    """Store each dataset's digest in its ``sha256`` attribute, then the root checksum."""
    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            obj.attrs["sha256"] = dataset_digest(obj)

    f.visititems(visit)
    f.attrs[CHECKSUM_ATTR] = manifest(f)


def seal(f: h5py.File) -> None:
    """Seal an asset open for writing: dataset digests, root checksum and, on close, the file hash.

    :func:`seal_content` runs now. The file hash of the user-block header
    (:func:`seal_file`) can only be computed once libhdf5 has written its last
    byte, so ``f.close`` (also called by ``with``) is wrapped to run
    :func:`seal_file` right after closing. Every writer that creates or edits
    an asset calls this last, before closing the file.
    """
    seal_content(f)
    if getattr(f, "_esmm_seal_file_on_close", False) or f.driver not in ("sec2", "stdio"):
        return
    name, close = f.filename, f.close

    def close_then_seal_file() -> None:
        was_open = bool(f.id.valid)
        close()
        if was_open:
            seal_file(name)

    f.close = close_then_seal_file
    f._esmm_seal_file_on_close = True


# -- the file header in the HDF5 user block ----------------------------------------------------
#
# libhdf5 can crash (SIGSEGV) or never return on damaged metadata, so a reader must know the
# bytes are the ones esmm wrote before it lets libhdf5 parse them. An asset starts with a user
# block of USERBLOCK_SIZE bytes (ignored by HDF5 readers: the superblock follows it) holding
#     b"ESMM-ASSET <version> sha256=<64 hex> length=<n>\n" + a note, zero padded,
# where the hash and length are those of every byte after the user block.

USERBLOCK_SIZE = 512
FILE_MAGIC = b"ESMM-ASSET"
FILE_HEADER_VERSION = 1
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_HEADER = re.compile(rb"ESMM-ASSET (\d{1,9}) sha256=([0-9a-f]{64}) length=(\d{1,20})\n")
_NOTE = (b"This is an HDF5 file (an esmm asset); the HDF5 data starts at byte 512. The line above is the "
         b"SHA-256 and size of every byte after this block, checked by esmm before the file is parsed.\n")
_CHUNK = 1 << 20


def create(path) -> h5py.File:
    """A new HDF5 file for an asset, with the user block that will carry the file header."""
    return h5py.File(path, "w", userblock_size=USERBLOCK_SIZE)


def _hash_after_userblock(fh) -> tuple[str, int]:
    fh.seek(USERBLOCK_SIZE)
    h, n = hashlib.sha256(), 0
    while chunk := fh.read(_CHUNK):
        h.update(chunk)
        n += len(chunk)
    return h.hexdigest(), n


def _header(digest: str, length: int) -> bytes:
    head = b"%s %d sha256=%s length=%d\n" % (FILE_MAGIC, FILE_HEADER_VERSION, digest.encode("ascii"), length)
    return (head + _NOTE).ljust(USERBLOCK_SIZE, b"\0")


def _prepend_userblock(path: Path) -> None:
    """Give an HDF5 file without a user block one of USERBLOCK_SIZE zero bytes (as h5jam does)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.ub-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as out, open(path, "rb") as src:
            out.write(bytes(USERBLOCK_SIZE))
            shutil.copyfileobj(src, out, _CHUNK)
        shutil.copymode(path, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    # libhdf5 finds the superblock at 512 and rebases the file; opening it once for writing
    # stores the new base address, so that the bytes hashed below are final.
    h5py.File(path, "r+").close()


def seal_file(path) -> bool:
    """Write the file header (hash and length of the bytes after the user block) of a closed asset.

    A file without a user block gets one first (the file is rewritten). A file
    whose user block holds something else than an esmm header or zeros (written
    by another tool) is left as it is.

    Returns
    -------
    bool
        Whether the header was written.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(USERBLOCK_SIZE + len(HDF5_SIGNATURE))
    if head.startswith(HDF5_SIGNATURE):
        _prepend_userblock(path)
    elif head[USERBLOCK_SIZE:] != HDF5_SIGNATURE or not (
            head.startswith(FILE_MAGIC) or not head[:USERBLOCK_SIZE].strip(b"\0")):
        return False
    with open(path, "r+b") as fh:
        digest, n = _hash_after_userblock(fh)
        fh.seek(0)
        fh.write(_header(digest, n))
    return True


def _remains_of_header(head: bytes) -> bool:
    """Whether a user block that is not a valid header still holds part of one.

    Any 16-byte piece of the note, the magic, ``sha256=`` or ``length=`` is a
    remain: a few damaged bytes cannot make an esmm file pass for one without a
    header (whose HDF5 parsing the hash no longer guards), as that would need
    about 300 bytes overwritten.
    """
    if FILE_MAGIC in head or b"sha256=" in head or b" length=" in head:
        return True
    return any(_NOTE[k:k + 16] in head for k in range(0, len(_NOTE) - 15, 16))


def check_file(path) -> tuple[bool, str]:
    """Check the file header before libhdf5 parses the file.

    Returns
    -------
    sealed : bool
        The file carries an esmm header (False: written by an older esmm or
        another tool; only the HDF5-level checks apply).
    problem : str
        "" when the header is absent or the bytes match it; otherwise one
        line: truncated, damaged or modified, or a newer header format.

    Raises
    ------
    OSError
        The file cannot be read.
    """
    with open(path, "rb") as fh:
        head = fh.read(USERBLOCK_SIZE)
        m = _HEADER.match(head)
        if m is None:
            if head.startswith(FILE_MAGIC):
                v = re.match(rb"ESMM-ASSET (\d{1,9}) ", head)
                if v and int(v.group(1)) > FILE_HEADER_VERSION:
                    return True, (f"written by a newer esmm (file header version {int(v.group(1))}, this esmm "
                                  f"reads {FILE_HEADER_VERSION}); upgrade esmm")
            if _remains_of_header(head):  # a header with damaged (or shifted) bytes
                return True, "damaged or modified after esmm wrote it (its esmm file header is unreadable)"
            return False, ""
        if int(m.group(1)) > FILE_HEADER_VERSION:
            return True, (f"written by a newer esmm (file header version {int(m.group(1))}, this esmm reads "
                          f"{FILE_HEADER_VERSION}); upgrade esmm")
        length = int(m.group(3))
        fh.seek(0, 2)
        have = fh.tell() - USERBLOCK_SIZE
        if have < length:
            return True, f"the file is truncated ({have + USERBLOCK_SIZE} of {length + USERBLOCK_SIZE} bytes)"
        if have > length:
            return True, (f"damaged or modified after esmm wrote it ({have - length} bytes more than written; "
                          f"file hash mismatch)")
        digest, _ = _hash_after_userblock(fh)
    if digest != m.group(2).decode("ascii"):
        return True, "damaged or modified after esmm wrote it (file hash mismatch)"
    return True, ""


def to_json(obj) -> str:
    """JSON text of a report (dataclass, dict, numpy values), keys sorted."""
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
