"""Where the network's force error comes from (issue 11; docs/validate.md §5, "Diagnosis").

Parts (``python scripts/force_diagnosis.py PART [options]``; one JSON line per
figure on stdout):

* ``strain``: the specimen cube (20 mm, gmsh like ``esmm prepare``) against the
  continuum in tension, compression and simple shear at strain ``--eps``
  (tension 1 + eps, compression 1 - eps, shear 2 eps), element sizes ``--sizes``,
  volume term ``--terms``: the signed force ratio network / continuum along the
  load, and the L2 and force errors of ``esmm validate``;
* ``radius``: the cube's cases at the validation loads (1.2, 0.9, 0.3) with the
  compensation calibrated on a cylinder of ``--radius`` element sizes instead of
  the default 4;
* ``shear-loss``: an experiment on the axial-only correction of before commit 689fbfe (not what
  ``esmm prepare`` does; on a joint-fit asset it corrects twice): the
  compensation's g multiplied by the calibration cylinder's own finite-strain
  loss in simple shear (its recorded shear checks, xy and xz, over their
  small-strain values, geometric mean with the small-strain factor's weights
  1 : 2 : 2, tension's loss 1), placed at the principal stretch
  ``gamma/2 + sqrt(1 + gamma^2/4)`` and at its inverse; then the cube's cases,
  or with ``--asset A.h5 --out B.h5`` a copy of an asset with those tables (to
  ``esmm validate B.h5``);
* ``timing``: the network side of ``esmm validate ASSET`` (``--cases``, volume
  term on), its tangent factored the old way (the LU with COLAMD) and the new
  (the LDLᵀ in node order, :func:`esmm.pipeline.network.newton.free_order`),
  in one process: seconds and the largest displacement difference.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time

import numpy as np
from esmm.pipeline.asset import read_asset
from esmm.pipeline.asset.rewrite import update_asset_tables
from esmm.pipeline.fidelity import network_solve
from esmm.pipeline.fidelity import validate as fv
from esmm.pipeline.fidelity.specimen import cube_specimen
from esmm.pipeline.materials.material import load_material
from esmm.pipeline.network.compensation import compensate, correction_on_grid
from esmm.pipeline.progress import ensure


def _rows(report, **extra):
    for c in report.figures()["cases"]:
        fc, fn = np.array(c["reaction_continuum_N"]), np.array(c["reaction_network_N"])
        print(json.dumps(dict(extra, case=c["case"], ratio=float(fn @ fc / (fc @ fc)), l2=c["l2_error"],
                              force=c["force_error"], nodes=report.info["nodes"], tets=report.info["tets"],
                              c=report.info["volume_factor"])), flush=True)


def strain(args, material):
    loads = fv.LoadOptions(tension=1 + args.eps, compression=1 - args.eps, gamma=2 * args.eps)
    for size in args.sizes:
        for term in args.terms:
            r = fv.validate_specimen(material, size=size * 1e-3, loads=loads, volume_term=term)
            _rows(r, part="strain", eps=args.eps, size_mm=size, term=term)


def radius(args, material):
    spec = cube_specimen(material, size=args.sizes[0] * 1e-3, volume=True, compensated=False)
    comp = compensate(spec.tables, spec.network, material=material, radius_elements=args.radius,
                      volume=spec.network.volume_term)
    r = fv.validate_network(spec.network, comp.tables, material, cases=list(fv.SPECIMEN_CASES), volume_term="on")
    _rows(r, part="radius", radius_elements=args.radius, size_mm=args.sizes[0])


def _shear_loss_tables(tables):
    """*tables* with g times the inverse of the cylinder's isotropic-average finite-strain shear loss."""
    law = tables.default_law
    rec = tables.metadata["compensation"]["laws"][law]
    knots, g, c = np.array(rec["knots"]), np.array(rec["g"]), rec["volume_factor"]
    small = rec["small_strain"]["cases"]
    gam = np.array(rec["checks"]["shear_xy"]["gamma"])
    xy = (1 + np.array(rec["checks"]["shear_xy"]["rel_error"])) / (c / small["xy"])
    xz = (1 + np.array(rec["checks"]["shear_xz"]["rel_error"])) / (c / small["xz"])
    loss = np.exp((2 * np.log(xy) + 2 * np.log(xz)) / 5)
    lam1 = gam / 2 + np.sqrt(1 + gam ** 2 / 4)
    hk = np.log(np.concatenate([1 / lam1[::-1], [1.0], lam1]))
    hv = np.log(np.concatenate([1 / loss[::-1], [1.0], 1 / loss]))
    base = tables.with_compensation(c, correction={law: np.ones(tables.n)})
    g2 = g * np.exp(np.interp(np.log(knots), hk, hv))
    print(json.dumps(dict(part="shear-loss", gamma=gam.tolist(), loss=loss.tolist(), at=lam1.tolist())), flush=True)
    return base.with_compensation(c, correction={law: correction_on_grid(base, knots, g2)})


def shear_loss(args, material):
    if args.asset:
        shutil.copy(args.asset, args.out)
        update_asset_tables(args.out, _shear_loss_tables(read_asset(args.asset).tables))
        return
    spec = cube_specimen(material, size=args.sizes[0] * 1e-3, volume=True)
    r = fv.validate_network(spec.network, _shear_loss_tables(spec.tables), material,
                            cases=list(fv.SPECIMEN_CASES), volume_term="on")
    _rows(r, part="shear-loss", size_mm=args.sizes[0])


def timing(args, _material):
    a = read_asset(args.asset)
    rep = ensure(None)
    terms = fv.network_terms(a.network, a.tables, a.material, volume_term="on")
    new = network_solve.free_order
    for name in args.cases:
        u = []
        for label, order in (("colamd", lambda _K, _free: None), ("node order", new)):
            network_solve.free_order = order
            case = fv._cases_for(a.network, [name], fv.LoadOptions(), rep)[0]
            t = time.perf_counter()
            if case.floor is None:
                s = network_solve.solve_network(case, a.network, a.tables, terms=terms, reporter=rep)
            else:
                s = fv._on_the_floor(case, lambda c, st: network_solve.solve_network(
                    c, a.network, a.tables, terms=terms, start=st, steps=1, reporter=rep), 10, rep)[0]
            u.append(s.displacement)
            print(json.dumps(dict(part="timing", case=name, ordering=label, seconds=time.perf_counter() - t)),
                  flush=True)
        network_solve.free_order = new
        print(json.dumps(dict(part="timing", case=name, max_difference_m=float(np.abs(u[0] - u[1]).max()))),
              flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("part", choices=("strain", "radius", "shear-loss", "timing"))
    p.add_argument("--eps", type=float, default=0.005)
    p.add_argument("--sizes", type=float, nargs="+", default=[4.0], help="element sizes, mm")
    p.add_argument("--terms", nargs="+", default=["on", "off"])
    p.add_argument("--radius", type=float, default=6.0, help="calibration cylinder radius, element sizes")
    p.add_argument("--asset", help="timing, shear-loss: the asset")
    p.add_argument("--out", help="shear-loss: the asset copy to write")
    p.add_argument("--cases", nargs="+", default=["lift"])
    args = p.parse_args()
    {"strain": strain, "radius": radius, "shear-loss": shear_loss, "timing": timing}[args.part](args, load_material("porcine_liver_paper"))


if __name__ == "__main__":
    main()
