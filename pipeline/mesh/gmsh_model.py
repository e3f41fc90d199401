"""A gmsh model in this process, for the small built-in specimens (cylinder, cube).

Organ meshes go through :mod:`.gmsh_worker` (a child process with a time limit);
the specimens of the virtual tensile test and of ``esmm validate`` are small and
meshed here, in one quiet model that is always removed again.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from ..errors import MeshingError

__all__ = ["gmsh_model", "tetrahedra"]


@contextlib.contextmanager
def gmsh_model(what: str) -> Iterator[Any]:
    """A fresh, quiet gmsh model; yields the ``gmsh`` module.

    gmsh is initialised if it is not yet (and finalised again on exit); the
    model is removed on exit. A MeshingError raised inside passes through; any
    other error becomes ``MeshingError("gmsh failed to mesh <what> (...); try
    another size")``.
    """
    import gmsh

    own = not gmsh.isInitialized()
    if own:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 1)
        gmsh.model.add(f"esmm_specimen_{id(object())}")
        yield gmsh
    except MeshingError:
        raise
    except Exception as exc:
        raise MeshingError(f"gmsh failed to mesh {what} ({exc}); try another size") from None
    finally:
        try:
            gmsh.model.remove()
        except Exception:  # pragma: no cover
            pass
        if own:
            gmsh.finalize()


def tetrahedra(gmsh: Any) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n, 3) in gmsh's units and linear tetrahedra (m, 4) as node indices of the current model."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    _, node_tags = gmsh.model.mesh.getElementsByType(4)
    pts = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    if len(node_tags) == 0:
        return pts, np.zeros((0, 4), np.int64)
    tags = np.asarray(tags, dtype=np.int64)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags] = np.arange(tags.size)
    return pts, index[np.asarray(node_tags, dtype=np.int64)].reshape(-1, 4)
