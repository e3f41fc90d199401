"""The outputs of ``esmm validate``: the table, the plots, the error fields for ParaView.

* :func:`table_rows` / :func:`table_markdown`: one row per case;
* :func:`plot_case`: ``<case>.png``, the continuum and the network side by side
  (deformed surface nodes coloured by the displacement magnitude, one colour
  scale) and the error;
* :func:`write_fields`: ``<case>.h5`` + ``<case>.xdmf``: the rest mesh with the
  two displacement fields, their difference and its magnitude (open the
  ``.xdmf`` in ParaView, "Xdmf Reader").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomicio import atomic_path, write_text
from ..network.springs import boundary_faces
from .compare import CaseResult

__all__ = ["table_rows", "table_markdown", "plot_case", "write_fields"]

_HEAD = ("case", "L2 error", "max error", "force error", "dV continuum", "dV network", "inverted c / n",
         "max |u| continuum")


def _pct(v: float) -> str:
    return "n/a" if not np.isfinite(v) else f"{100 * v:.2f} %"


def table_rows(results) -> list[list[str]]:
    """The table's cells: one row per case (percentages, mm)."""
    rows = []
    for r in results:
        name = r.case.name                      # marked with its element if P2 found no equilibrium
        if "element_fallback" in r.continuum.info:
            name += f" ({r.continuum.info['element']})"
        rows.append([name, _pct(r.l2_error), _pct(r.max_error), _pct(r.force_error),
                     _pct(r.continuum.volume_ratio - 1), _pct(r.network.volume_ratio - 1),
                     f"{r.continuum.inverted} / {r.network.inverted}", f"{r.max_displacement_m * 1e3:.3g} mm"])
    return rows


def table_markdown(results) -> str:
    """The table as Markdown (docs and the report)."""
    lines = ["| " + " | ".join(_HEAD) + " |", "|" + " --- |" * len(_HEAD)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(results)]
    return "\n".join(lines)


def _view(points: np.ndarray, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Two in-plane axes: horizontal and up when there is gravity, else the two largest extents."""
    if np.any(gravity):
        up = -gravity / np.linalg.norm(gravity)
        ext = np.ptp(points - np.outer(points @ up, up), axis=0)
        h = np.eye(3)[int(np.argmax(ext))]
        h = h - (h @ up) * up
        return h / np.linalg.norm(h), up, "side view (up is up)"
    order = np.argsort(np.ptp(points, axis=0))[::-1]
    return np.eye(3)[order[0]], np.eye(3)[order[1]], f"view along {'xyz'[order[2]]}"


def plot_case(result: CaseResult, png_path) -> Path:
    """Draw the continuum and the network deformed side by side, and the error, into *png_path*."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    case = result.case
    surf = np.unique(boundary_faces(case.tets))
    X = case.points
    ex, ey, label = _view(X, case.gravity)
    uc, un = result.continuum.displacement, result.network.displacement
    vmax = max(float(np.linalg.norm(uc, axis=1).max()), float(np.linalg.norm(un, axis=1).max())) * 1e3 or 1.0
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6), dpi=110, sharex=True, sharey=True)
    panels = ((uc, "continuum (FE)"), (un, "spring network"))
    for ax, (u, title) in zip(axes[:2], panels):
        Y = X[surf] + u[surf]
        sc = ax.scatter(Y @ ex * 1e3, Y @ ey * 1e3, c=np.linalg.norm(u[surf], axis=1) * 1e3, s=4, cmap="viridis",
                        vmin=0, vmax=vmax)
        ax.scatter(X[surf] @ ex * 1e3, X[surf] @ ey * 1e3, s=0.3, c="0.8", zorder=0)
        ax.set_title(title)
    fig.colorbar(sc, ax=axes[:2], label="displacement [mm]", shrink=0.85)
    err = np.linalg.norm(result.error_field[surf], axis=1) * 1e3
    Y = X[surf] + uc[surf]
    sc2 = axes[2].scatter(Y @ ex * 1e3, Y @ ey * 1e3, c=err, s=4, cmap="magma")
    axes[2].set_title("|network - continuum|")
    fig.colorbar(sc2, ax=axes[2], label="[mm]", shrink=0.85)
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_xlabel("mm")
    axes[0].set_ylabel(f"mm ({label}; grey: rest)")
    fig.suptitle(f"{case.name}: L2 error {_pct(result.l2_error)}, max {_pct(result.max_error)}, "
                 f"force {_pct(result.force_error)}", fontsize=11)
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(png_path)


_XDMF = """<?xml version="1.0" ?>
<Xdmf Version="3.0">
  <Domain>
    <Grid Name="{name}" GridType="Uniform">
      <Topology TopologyType="Tetrahedron" NumberOfElements="{t}">
        <DataItem Dimensions="{t} 4" NumberType="Int" Precision="8" Format="HDF">{h5}:/tets</DataItem>
      </Topology>
      <Geometry GeometryType="XYZ">
        <DataItem Dimensions="{n} 3" NumberType="Float" Precision="8" Format="HDF">{h5}:/points</DataItem>
      </Geometry>
{attributes}
    </Grid>
  </Domain>
</Xdmf>
"""

_ATTR = """      <Attribute Name="{key}" AttributeType="{kind}" Center="Node">
        <DataItem Dimensions="{dims}" NumberType="Float" Precision="8" Format="HDF">{h5}:/{key}</DataItem>
      </Attribute>"""


def write_fields(result: CaseResult, xdmf_path) -> Path:
    """``<name>.h5`` (rest mesh, both displacements, error) and its ``<name>.xdmf`` for ParaView [m]."""
    import h5py

    xdmf_path = Path(xdmf_path)
    h5_path = xdmf_path.with_suffix(".h5")
    case = result.case
    fields = {"u_continuum": result.continuum.displacement, "u_network": result.network.displacement,
              "error": result.error_field, "error_magnitude": np.linalg.norm(result.error_field, axis=1)}
    with atomic_path(h5_path) as tmp, h5py.File(tmp, "w") as f:
        f["points"] = case.points
        f["tets"] = case.tets.astype(np.int64)
        for key, value in fields.items():
            f[key] = value
            f[key].attrs["units"] = "m"
    attrs = "\n".join(_ATTR.format(key=k, kind="Vector" if v.ndim == 2 else "Scalar",
                                   dims=" ".join(str(d) for d in v.shape), h5=h5_path.name)
                      for k, v in fields.items())
    write_text(xdmf_path, _XDMF.format(name=case.name, t=case.tets.shape[0], n=case.n_nodes, h5=h5_path.name,
                                       attributes=attrs))
    return xdmf_path
