"""The volume term's study (docs/design/model.md, "The volume term (nearly incompressible network)"): locking, Poisson ratio, bulk modulus, transfer.

Parts (``python scripts/volume_study.py PART [PART ...]``, results merged into
``docs/figures/volume_study.json``):

* ``small``: small-strain uniaxial tension (free sides) and simple shear of a
  gmsh cylinder (R 5 mm, H 20 mm, h 2.5 mm), raw springs (c = 1), with the
  nodal and the per-tet volume term at kappa / mu0 = 0 ... 1e4: the network's
  Young's modulus, apparent Poisson ratio, volume change and shear modulus;
* ``locking``: a cantilever under its own weight (linear solve at rest),
  clamped gmsh cylinder (R 5, H 50, h 2.5 mm) and a structured Kuhn box
  (100 x 20 x 20 mm, 20 x 4 x 4 cells): tip deflection against kappa / mu0;
* ``kappa``: the compensation calibrated with the volume term at
  kappa / mu_t = 1 ... 100 on the h 2.5 mm cylinder: volume change and
  lateral stretch at 1.3 and 0.9, errors, and the explicit step it allows
  on the bundled liver;
* ``transfer``: the compensation of the default specimen (radius 4 element
  sizes) checked on other cylinders (radius 2, 3, 6 element sizes) and, by
  homogeneous deformations of the whole boundary, on organ networks
  (``--organ ASSET.h5``, several allowed);
* ``record``: the compensation record each ``--organ`` asset carries (the
  calibration ``esmm prepare`` ran: c, its three small-strain factors, the
  stretch correction, errors, shear checks, volume change).

Takes tens of minutes (``transfer`` most).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spl
from esmm.pipeline.asset import read_asset
from esmm.pipeline.compensation.calibration import calibrate_compensation
from esmm.pipeline.compensation.loadcases import (
    homogeneous_test,
    shear_deformation,
    virtual_shear_test,
)
from esmm.pipeline.compensation.virtual_tensile import cylinder_specimen, virtual_tensile_test
from esmm.pipeline.materials.loading import energy_density
from esmm.pipeline.materials.material import load_material
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.forcelaw import tangent_stiffness
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.network.tables import build_tables
from esmm.pipeline.network.volume import (
    VolumeSpec,
    bulk_modulus,
    bulk_ratio,
    tangent_shear_modulus,
    volume_elements,
)
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.stepper import stable_step
from esmm.pipeline.simulate.volumeterm import build_volume_term

OUT = Path(__file__).resolve().parent.parent / "docs" / "figures" / "volume_study.json"
RATIOS = (0, 1, 10, 100, 1000, 10000)


def small(mat, tb):
    """Small-strain moduli of the raw network with the volume term."""
    mu0, _ = tangent_shear_modulus(tb, 0.999, 1.001)
    spec = cylinder_specimen(radius=5e-3, length=20e-3, size=2.5e-3)
    eps = 1e-3
    rows = []
    for form in ("nodal", "tet"):
        for r in RATIOS:
            vol = None if r == 0 else VolumeSpec(r * mu0, form)
            t = virtual_tensile_test(spec, tb, stretch=[1 + eps], law="secant", volume=vol, material=mat)
            s = virtual_shear_test(spec.network, tb, gamma=[eps], law="secant", volume=vol, material=mat)
            E = float(t.stress[0] / t.reference[0])
            rows.append({"formulation": form, "kappa_over_mu0": r, "E_net_over_E": E,
                         "poisson": float(-(t.lateral_stretch[0] - 1) / eps),
                         "dV_over_V_per_strain": float((t.volume_ratio[0] - 1) / eps),
                         "mu_net_over_mu": s.shear_modulus_ratio, "E_over_3mu_net": E / s.shear_modulus_ratio})
            print(rows[-1], flush=True)
    return {"specimen": spec.describe(), "mu0_pa": mu0, "rows": rows}


def _cantilever(net, tb, clamp, tip, load, mu0):
    X = net.points
    Ks = tangent_stiffness(X, net, tb, law="secant")
    fixed = np.zeros((X.shape[0], 3), bool)
    fixed[clamp] = True
    free = ~fixed.ravel()
    f = (net.mass[:, None] * 9.81 * load[None, :]).ravel()
    out = {}
    for form in ("nodal", "tet"):
        for r in RATIOS:
            K = Ks if r == 0 else (Ks + volume_elements(X, net.tets, VolumeSpec(r * mu0, form)).tangent(X)).tocsr()
            u = np.zeros(3 * X.shape[0])
            u[free] = spl.spsolve(K[free][:, free].tocsc(), f[free])
            out[f"{form}:{r}"] = float((u.reshape(-1, 3)[tip] @ load).mean())
    w0 = out["nodal:0"]
    return {k: v / w0 for k, v in out.items()}


def locking(mat, tb):
    """Cantilever deflection against kappa / mu0, nodal against per-tet."""
    mu0, _ = tangent_shear_modulus(tb, 0.999, 1.001)
    spec = cylinder_specimen(radius=5e-3, length=50e-3, size=2.5e-3)
    net = spec.network
    tip = np.flatnonzero(np.abs(net.points[:, 2] - 50e-3) < 1e-9)
    cyl = _cantilever(net, tb, spec.bottom, tip, np.array([1.0, 0, 0]), mu0)
    box = network_from_tets(box_tets(20, 4, 4, (0.1, 0.02, 0.02)))
    X = box.points
    kuhn = _cantilever(box, tb, np.flatnonzero(X[:, 0] < 1e-9), np.flatnonzero(X[:, 0] > 0.1 - 1e-9),
                       np.array([0, 0, -1.0]), mu0)
    print(cyl, kuhn, flush=True)
    return {"cylinder_R5_H50_h2.5": cyl, "kuhn_box_20x4x4": kuhn, "note": "tip deflection / springs alone"}


def kappa(mat, tb, organ: str | None):
    """The compensation calibrated at several kappa / mu_t: volume change, errors, explicit step."""
    spec = cylinder_specimen(radius=5e-3, length=20e-3, size=2.5e-3)
    mu_t, at = tangent_shear_modulus(tb, 0.9, 1.3)
    net = read_asset(organ).network if organ else None
    rows = []
    for r in (1, 3, 10, 30, 50, 100):
        vol = VolumeSpec(r * mu_t, "nodal")
        t = time.time()
        comp, res = calibrate_compensation(tb, spec, law="secant", material=mat, volume=vol)
        rec = res.record()
        row = {"kappa_over_mu_t": r, "kappa_pa": vol.bulk_modulus, "nu_equivalent": (3 * r - 2) / (6 * r + 2),
               "c": res.factor, "dV_at_0.9": float(res.after.volume_ratio[0] - 1),
               "dV_at_1.3": float(res.after.volume_ratio[-1] - 1),
               "lateral_at_1.3": float(res.after.lateral_stretch[-1]),
               "tension_max_err": rec["errors_after"]["max_abs_rel_error"],
               "shear_xz_err": rec["checks"]["shear_xz"]["rel_error"],
               "shear_xy_err": rec["checks"]["shear_xy"]["rel_error"], "seconds": time.time() - t}
        if net is not None:
            springs = build_spring_term(net, comp)
            vt = build_volume_term(net.points, net.tets, vol, lam_max=comp.lam_max)
            row["liver_dt_window_us"] = stable_step([springs, vt], net.mass, x=net.points, window=0.05).dt * 1e6
            row["liver_dt_window_springs_us"] = stable_step([springs], net.mass, x=net.points, window=0.05).dt * 1e6
        rows.append(row)
        print(row, flush=True)
    return {"mu_t_pa": mu_t, "at_stretch": at, "nu_049_ratio": bulk_ratio(0.49), "rows": rows}


def _organ_check(net, comp, mat, vol):
    """Energy of homogeneous deformations of the whole boundary over the continuum's, per case."""
    out = {}
    for ax in range(3):
        for group in ((0.95, 0.9), (1.1, 1.2)):
            Fs = []
            for lam in group:
                F = np.eye(3) * lam ** -0.5
                F[ax, ax] = lam
                Fs.append(F)
            r = homogeneous_test(net, comp, Fs, law=comp.default_law, volume=vol, substeps=2)
            ref = np.array([float(energy_density(mat.model_obj, mat.params, "uniaxial", lam)) for lam in group])
            for lam, e, j, inv in zip(group, r.energy / (ref * r.rest_volume), r.volume_ratio, r.inverted):
                out[f"uniaxial_{'xyz'[ax]}_{lam:g}"] = {"energy_ratio": float(e), "volume_ratio": float(j),
                                                         "inverted": int(inv)}
    for plane in ("xy", "yz", "xz"):
        gs = (0.1, 0.2)
        r = homogeneous_test(net, comp, [shear_deformation(g, plane) for g in gs], law=comp.default_law,
                             volume=vol, substeps=2)
        ref = np.array([float(energy_density(mat.model_obj, mat.params, "simple_shear", g)) for g in gs])
        for g, e in zip(gs, r.energy / (ref * r.rest_volume)):
            out[f"shear_{plane}_{g:g}"] = {"energy_ratio": float(e)}
    return out


def transfer(mat, tb, organs):
    """The default calibration (radius 4 elements) on other cylinders and on organ networks."""
    h = 1e-3
    vol = bulk_modulus(tb)
    base = cylinder_specimen(radius=4 * h, length=16 * h, size=h)
    comp, res = calibrate_compensation(tb, base, law="secant", material=mat, volume=vol)
    out = {"calibration": res.record(), "cylinders": {}, "organs": {}}
    lam_t, lam_c = np.linspace(1.05, 1.3, 6), np.array([0.97, 0.94, 0.9])
    for R in (2, 3, 6):
        spec = cylinder_specimen(radius=R * h, length=4 * R * h, size=h)
        t = virtual_tensile_test(spec, comp, stretch=lam_t, law="secant", material=mat, volume=vol)
        c = virtual_tensile_test(spec, comp, stretch=lam_c, law="secant", material=mat, volume=vol)
        s = {p: virtual_shear_test(spec.network, comp, gamma=(0.1, 0.2, 0.3), law="secant", material=mat,
                                   volume=vol, plane=p).rel_error.tolist() for p in ("xy", "xz")}
        out["cylinders"][f"R{R}h"] = {"nodes": spec.n_nodes, "tension_err": t.rel_error.tolist(),
                                      "compression_err": c.rel_error.tolist(), "shear_err": s}
        print(R, out["cylinders"][f"R{R}h"], flush=True)
    for path in organs:
        net = read_asset(path).network
        out["organs"][Path(path).stem] = {"nodes": net.n_nodes, "cases": _organ_check(net, comp, mat, vol)}
        print(path, out["organs"][Path(path).stem], flush=True)
    return out


def record(organs):
    """The compensation record stored in each organ asset (what ``esmm prepare`` calibrated)."""
    out = {}
    for path in organs:
        rec = read_asset(path).tables.metadata["compensation"]
        out[Path(path).stem] = rec["laws"] if "laws" in rec else rec
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("parts", nargs="+", choices=("small", "locking", "kappa", "transfer", "record"))
    ap.add_argument("--organ", action="append", default=[], help="organ asset for 'kappa' (first) and 'transfer'")
    args = ap.parse_args(argv)
    mat = load_material("porcine_liver_paper")
    tb = build_tables(mat)
    data = json.loads(OUT.read_text()) if OUT.exists() else {}
    for part in args.parts:
        t = time.time()
        if part == "kappa":
            data[part] = kappa(mat, tb, args.organ[0] if args.organ else None)
        elif part == "transfer":
            data[part] = transfer(mat, tb, args.organ)
        elif part == "record":
            data[part] = record(args.organ)
        else:
            data[part] = {"small": small, "locking": locking}[part](mat, tb)
        data[part]["seconds"] = time.time() - t
        OUT.parent.mkdir(parents=True, exist_ok=True)
        OUT.write_text(json.dumps(data, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
