"""Where the network's force error comes from (docs/design/validation.md, "What the network's errors are, and why").

Parts (``python scripts/force_diagnosis.py PART [options]``; one JSON line per
figure on stdout):

* ``strain``: the specimen cube (20 mm, gmsh like ``esmm prepare``) against the
  continuum in tension, compression and simple shear at strain ``--eps``
  (tension 1 + eps, compression 1 - eps, shear 2 eps), element sizes ``--sizes``,
  volume term ``--terms``: the signed force ratio network / continuum along the
  load, and the L2 and force errors of ``esmm validate``;
* ``radius``: the cube's cases at the validation loads (1.2, 0.9, 0.3) at each of
  ``--sizes`` with the compensation calibrated on a cylinder of ``--radius`` element
  sizes instead of the default 4;
* ``shear-loss``: an experiment on the axial-only stretch correction (fitted on the uniaxial test alone; not what
  ``esmm prepare`` does; on a joint-fit asset it corrects twice): the
  compensation's g multiplied by the calibration cylinder's own finite-strain
  loss in simple shear (its recorded shear checks, xy and xz, over their
  small-strain values, geometric mean with the small-strain factor's weights
  1 : 2 : 2, tension's loss 1), placed at the principal stretch
  ``gamma/2 + sqrt(1 + gamma^2/4)`` and at its inverse; then the cube's cases,
  or with ``--asset A.h5 --out B.h5`` a copy of an asset with those tables (to
  ``esmm validate B.h5``);
* ``fabric``: an experiment on the springs' volume shares (not what ``esmm prepare`` does):
  the cube's network at each of ``--sizes`` under six homogeneous small strains (every boundary
  node on the affine field, the interior relaxed; ``--affine``: not relaxed), its strain energy
  over the continuum's ``V e:C:e / 2`` with the springs' own Cauchy material (lambda = mu), for
  the shares ``V_t / 6`` (``esmm prepare``), per-tet fitted shares (non-negative least squares
  of each tet's six springs against ``V_t C``; Lloyd et al. 2007's idea) and a global
  reweighting that makes the network's orientation fabric isotropic (:func:`_isotropic_factors`);
  with ``--validate``, the cube's cases at each size as ``radius`` gives them (``--radius 4``:
  ``esmm validate --specimen``'s calibration), or with ``--prepare STL --out A.h5`` ``esmm prepare
  STL --config paper``, with the isotropic fabric (its calibrations cached apart, in the cache's
  ``fabric-experiment`` folder);
* ``timing``: the network side of ``esmm validate ASSET`` (``--cases``, volume
  term on), its tangent factored two ways (the LU with COLAMD, and the LDLᵀ in
  node order of :func:`esmm.pipeline.linalg.newton.free_order`),
  in one process: seconds and the largest displacement difference.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import time

import numpy as np
import scipy.sparse.linalg as spla
from esmm.pipeline import cache
from esmm.pipeline.asset import read_asset
from esmm.pipeline.asset.rewrite import update_asset_tables
from esmm.pipeline.compensation.calibration import compensate, correction_on_grid
from esmm.pipeline.fidelity import network_solve
from esmm.pipeline.fidelity import validate as fv
from esmm.pipeline.fidelity.specimen import cube_specimen
from esmm.pipeline.materials.material import load_material
from esmm.pipeline.network import springs
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


def radius(args, material, part="radius"):
    for size in args.sizes:
        spec = cube_specimen(material, size=size * 1e-3, volume=True, compensated=False)
        comp = compensate(spec.tables, spec.network, material=material, radius_elements=args.radius,
                          volume=spec.network.volume_term)
        r = fv.validate_network(spec.network, comp.tables, material, cases=list(fv.SPECIMEN_CASES),
                                volume_term="on")
        _rows(r, part=part, radius_elements=args.radius, size_mm=size)


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

#: Exponents (a, b, c) of the 15 monomials x^a y^b z^c of degree 4: a fully symmetric 4th-order tensor's components.
_EXP = np.array([[a, b, 4 - a - b] for a in range(4, -1, -1) for b in range(4 - a, -1, -1)])
#: Voigt pairs and the Cauchy material (lambda = mu = 1) the springs have, in Voigt form (engineering shears).
_VOIGT = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))
_CAUCHY = np.block([[np.ones((3, 3)) + 2 * np.eye(3), np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3)]])


def _odd_free_average(a, b, c):
    """The mean of x^a y^b z^c over the unit sphere (degree 4): (a-1)!!(b-1)!!(c-1)!! / 15, 0 if one is odd."""
    if a % 2 or b % 2 or c % 2:
        return 0.0
    df = {0: 1, 2: 1, 4: 3}
    return df[a] * df[b] * df[c] / 15.0


def _isotropic_factors(n, q):
    r"""Per-spring factors m that make the fabric isotropic: ``sum_s q_s m_s M(n_s) = alpha <M>`` with
    ``M(n)`` the 15 degree-4 monomials of the spring's direction, ``<M>`` their sphere average (the
    fabric of an isotropic network), ``sum q m = sum q``. With ``m = M(n) . gamma`` (degree-4
    polynomials span the harmonics of degree 0, 2 and 4 on the sphere: the closest such factors to 1
    in the q-weighted norm), ``gamma = alpha G^{-1} <M>``, ``G = sum q M M^T``. The network's affine
    elasticity ``sum k L^2 nnnn / V`` is then isotropic (Cauchy's lambda = mu)."""
    M = np.prod(n[:, None, :] ** _EXP[None, :, :], axis=2)
    avg = np.array([_odd_free_average(*e) for e in _EXP])
    m = M @ np.linalg.lstsq((M * q[:, None]).T @ M, avg, rcond=None)[0]
    return m * q.sum() / (q * m).sum()


def _per_tet_factors(net):
    """The spring volume shares from each tet's six springs fitted to ``V_t C`` (non-negative least squares,
    the Voigt matrices whole), over ``V_ij``: the factors to apply to ``v_ij``."""
    from scipy.optimize import nnls
    key = {tuple(p): i for i, p in enumerate(net.springs)}
    vt = springs.tet_volumes(net.points, net.tets)
    share = np.zeros(net.n_springs)
    iu = np.triu_indices(6)
    for t, tet in enumerate(net.tets):
        cols, idx = [], []
        for p, q in springs._TET_EDGES:
            d = net.points[tet[q]] - net.points[tet[p]]
            a = np.array([d[i] * d[j] for i, j in _VOIGT]) / np.linalg.norm(d)     # L n_i n_j
            cols.append(np.outer(a, a)[iu])
            idx.append(key[tuple(sorted((tet[p], tet[q])))])
        k = nnls(np.array(cols).T, (vt[t] * _CAUCHY)[iu])[0]
        np.add.at(share, idx, k * np.array([net.rest_length[i] ** 2 for i in idx]))
    return share / net.volume


def _patch_ratios(net, *, affine=False):
    """The network's energy over the continuum's in six homogeneous strains (module doc, ``fabric``)."""
    K = springs.stiffness_matrix(net).tocsr()
    inner = np.ones(net.n_nodes, bool)
    inner[np.unique(net.surface_faces)] = False
    f, b = np.repeat(inner, 3), np.repeat(~inner, 3)
    Kff, Kfb = K[f][:, f].tocsc(), K[f][:, b]
    out = []
    for i, j in _VOIGT:
        eps = np.zeros((3, 3))
        eps[i, j] = eps[j, i] = 1e-3
        u = ((net.points - net.points.mean(0)) @ eps.T).ravel()
        if not affine:
            u[f] = spla.spsolve(Kff, -(Kfb @ u[b]))
        ev = np.array([eps[p, q] * (1 if p == q else 2) for p, q in _VOIGT])
        out.append(float(u @ (K @ u)) / float(net.total_volume() * ev @ _CAUCHY @ ev))
    return out


def _reweighted(net, m):
    return dataclasses.replace(net, volume=net.volume * m, volume_weight=net.volume_weight * m)


def _isotropic(net):
    d = net.points[net.springs[:, 1]] - net.points[net.springs[:, 0]]
    return _isotropic_factors(d / np.linalg.norm(d, axis=1)[:, None], net.volume)


def fabric(args, material):
    for size in args.sizes:
        net = cube_specimen(material, size=size * 1e-3, volume=False, compensated=False).network
        for name, m in (("volume", np.ones(net.n_springs)), ("per-tet", _per_tet_factors(net)),
                        ("isotropic", _isotropic(net))):
            r = _patch_ratios(_reweighted(net, m), affine=args.affine)
            print(json.dumps(dict(part="fabric", size_mm=size, shares=name, affine=args.affine,
                                  factors=[float(m.min()), float(m.max())], ratios=r,
                                  spread=max(r) / min(r))), flush=True)
    if not (args.validate or args.prepare):
        return
    from esmm.pipeline.compensation import virtual_tensile as tt
    from esmm.pipeline.fidelity import specimen as fs
    base = springs.network_from_tets

    def builder(*a, **k):
        net = base(*a, **k)
        return _reweighted(net, _isotropic(net))

    os.environ["ESMM_CACHE_DIR"] = str(cache.root() / "fabric-experiment")
    from esmm.pipeline import prepare as pp
    for mod in (fs, tt, pp):
        mod.network_from_tets = builder
    if args.prepare:
        from esmm.cli.main import main as cli
        cli(["prepare", args.prepare, "--config", "paper", "-o", args.out])
        return
    radius(args, material, part="fabric-validate")


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
    p.add_argument("part", choices=("strain", "radius", "shear-loss", "fabric", "timing"))
    p.add_argument("--eps", type=float, default=0.005)
    p.add_argument("--sizes", type=float, nargs="+", default=[4.0], help="element sizes, mm")
    p.add_argument("--terms", nargs="+", default=["on", "off"])
    p.add_argument("--radius", type=float, default=6.0, help="calibration cylinder radius, element sizes")
    p.add_argument("--asset", help="timing, shear-loss: the asset")
    p.add_argument("--out", help="shear-loss: the asset copy to write")
    p.add_argument("--cases", nargs="+", default=["lift"])
    p.add_argument("--affine", action="store_true", help="fabric: the strain energies unrelaxed")
    p.add_argument("--validate", action="store_true", help="fabric: validate the cube with the isotropic fabric")
    p.add_argument("--prepare", help="fabric: prepare this surface with the isotropic fabric (to --out)")
    args = p.parse_args()
    parts = {"strain": strain, "radius": radius, "shear-loss": shear_loss, "fabric": fabric, "timing": timing}
    parts[args.part](args, load_material("porcine_liver_paper"))


if __name__ == "__main__":
    main()
