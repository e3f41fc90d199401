"""Run gmsh (and fTetWild) in a child process with a time limit.

gmsh can loop forever on some inputs (zero-volume islands, degenerate patches)
and can abort the whole process on others; fTetWild can run for very long. So
neither runs in the caller's process: :func:`run_worker` writes the input to a
temporary folder, starts ``python -m esmm.pipeline.mesh.gmsh_worker`` in its
own process group, waits at most ``timeout`` seconds, and kills the group if it
has not finished. The child writes ``out.npz`` (arrays) and ``out.json``
(figures, log lines) or ``error.json``.

Commands
--------
``read``
    ``{"path"}`` -> ``nodes`` (n, 3), ``triangles`` (m, 3), ``tets`` (t, 4)
    (0-based, file units): gmsh reads any MSH version, including MSH 1.
``mesh``
    ``points``, ``faces`` and ``{"size", "angle_deg", "algorithm3d",
    "threads", "optimize_netgen"}`` -> ``nodes``, ``tets``: remesh the
    surface (classifySurfaces with reparametrisation, createGeometry) and fill
    it with tetrahedra of size ``size`` (same units as the points).
``tetwild``
    ``points``, ``faces`` and ``{"edge_length", "epsilon"}`` -> ``nodes``,
    ``tets``: fTetWild (pytetwild), robust to self-intersections.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


class GmshFailure(RuntimeError):
    """The child failed; the message is its error (one line) and ``log`` its output."""

    def __init__(self, message: str, log: list[str] | None = None):
        super().__init__(message)
        self.log = log or []


class GmshTimeout(GmshFailure):
    """The child did not finish in time and was killed (``pid`` is its process id)."""

    def __init__(self, message: str, log: list[str] | None = None, pid: int | None = None):
        super().__init__(message, log)
        self.pid = pid


def run_worker(command: str, options: dict, *, arrays: dict[str, np.ndarray] | None = None,
               timeout: float = 120.0) -> dict:
    """Run *command* in a child process; return its arrays and figures.

    Parameters
    ----------
    command
        ``"read"``, ``"mesh"`` or ``"tetwild"``.
    options
        JSON-serialisable options of the command.
    arrays
        Input arrays (``points`` (n, 3), ``faces`` (m, 3)).
    timeout
        Seconds before the child (and anything it started) is killed.

    Returns
    -------
    dict
        The output arrays, plus ``"info"`` (dict) and ``"log"`` (list of str).

    Raises
    ------
    GmshTimeout
        The time limit was reached; the child was killed.
    GmshFailure
        The child reported an error or died.
    """
    with tempfile.TemporaryDirectory(prefix="esmm-gmsh-") as tmp:
        d = Path(tmp)
        (d / "in.json").write_text(json.dumps({"command": command, "options": options}))
        np.savez(d / "in.npz", **(arrays or {}))
        env = dict(os.environ)
        env.setdefault("OMP_NUM_THREADS", str(options.get("threads", 1)))
        with open(d / "stdout.txt", "wb") as out:
            proc = subprocess.Popen(
                child_argv(d),
                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                start_new_session=True, env=env, cwd=d,  # fTetWild writes __tracked_surface.stl in its cwd
            )
            try:
                code = proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                _kill_group(proc)
                log = _tail(d / "stdout.txt")
                raise GmshTimeout(f"{command}: no result after {timeout:g} s; the process was killed",
                                  log, pid=proc.pid) from None
            except BaseException:  # Ctrl-C in the parent: do not leave the child running
                _kill_group(proc)
                raise
        log = _tail(d / "stdout.txt")
        if (d / "error.json").exists():
            err = json.loads((d / "error.json").read_text())
            raise GmshFailure(err.get("error", "unknown error"), err.get("log", []) or log)
        if code != 0 or not (d / "out.npz").exists():
            last = next((ln for ln in reversed(log) if ln.strip()), "")
            reason = f"signal {-code}" if code < 0 else f"exit code {code}"
            raise GmshFailure(f"{command}: the process died ({reason}){': ' + last if last else ''}", log)
        with np.load(d / "out.npz") as z:
            result = {k: z[k] for k in z.files}
        info = json.loads((d / "out.json").read_text())
        result["info"] = info.get("info", {})
        result["log"] = info.get("log", []) or log
        return result


def child_argv(folder: Path) -> list[str]:
    """The command line of the child that works in *folder*.

    One function so that a test can put a child in its place that cannot
    finish (the time limit and the kill of its process group are then tested
    by what they do, not by how fast this machine meshes).
    """
    return [sys.executable, "-m", "esmm.pipeline.mesh.gmsh_worker", str(folder)]


def _kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(Exception):
        proc.wait(timeout=10)


def _tail(path: Path, n: int = 200) -> list[str]:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    return lines[-n:]


# ------------------------------------------------------------------ child
def _gmsh_start(threads: int = 1):
    import gmsh

    gmsh.initialize(["gmsh", "-noenv"], readConfigFiles=False, interruptible=False)
    gmsh.option.setNumber("General.Terminal", 1)
    gmsh.option.setNumber("General.Verbosity", 4)
    gmsh.option.setNumber("General.NumThreads", max(1, int(threads)))
    gmsh.logger.start()
    return gmsh


def _cmd_read(opts: dict, arrays: dict) -> tuple[dict, dict]:
    gmsh = _gmsh_start()
    gmsh.open(opts["path"])
    tags, coords, _ = gmsh.model.mesh.getNodes()
    if tags.size == 0:
        raise RuntimeError("no nodes in the file")
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    nodes = coords.reshape(-1, 3)
    out = {"nodes": nodes, "triangles": np.zeros((0, 3), np.int64), "tets": np.zeros((0, 4), np.int64)}
    for etype, key, k in ((2, "triangles", 3), (4, "tets", 4)):
        _, ntags = gmsh.model.mesh.getElementsByType(etype)
        if len(ntags):
            out[key] = index[np.asarray(ntags, np.int64)].reshape(-1, k)
    info = {"n_nodes": int(tags.size)}
    return out, info


def _cmd_mesh(opts: dict, arrays: dict) -> tuple[dict, dict]:
    import math

    gmsh = _gmsh_start(opts.get("threads", 1))
    pts = np.asarray(arrays["points"], np.float64)
    faces = np.asarray(arrays["faces"], np.int64)
    size = float(opts["size"])
    t0 = time.perf_counter()
    gmsh.model.add("organ")
    gmsh.model.addDiscreteEntity(2, 1)
    gmsh.model.mesh.addNodes(2, 1, np.arange(1, pts.shape[0] + 1), pts.ravel())
    gmsh.model.mesh.addElementsByType(1, 2, [], (faces + 1).ravel())
    angle = math.radians(float(opts.get("angle_deg", 180.0)))
    gmsh.model.mesh.classifySurfaces(angle, True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    surfaces = [s[1] for s in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(surfaces)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.6 * size)
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    gmsh.option.setNumber("Mesh.Algorithm", int(opts.get("algorithm2d", 5)))
    gmsh.option.setNumber("Mesh.Algorithm3D", int(opts.get("algorithm3d", 1)))
    gmsh.option.setNumber("Mesh.Optimize", 1 if opts.get("optimize", True) else 0)
    gmsh.option.setNumber("Mesh.OptimizeNetgen", 1 if opts.get("optimize_netgen", True) else 0)
    gmsh.option.setNumber("Mesh.MaxNumThreads3D", max(1, int(opts.get("threads", 1))))
    t1 = time.perf_counter()
    gmsh.model.mesh.generate(2)
    t2a = time.perf_counter()
    gmsh.model.mesh.generate(3)
    t2 = time.perf_counter()
    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    _, ntags = gmsh.model.mesh.getElementsByType(4)
    tets = index[np.asarray(ntags, np.int64)].reshape(-1, 4) if len(ntags) else np.zeros((0, 4), np.int64)
    info = {"n_patches": len(surfaces), "t_geometry": t1 - t0, "t_surface": t2a - t1, "t_volume": t2 - t2a}
    return {"nodes": coords.reshape(-1, 3), "tets": tets}, info


def _cmd_tetwild(opts: dict, arrays: dict) -> tuple[dict, dict]:
    import pytetwild

    t0 = time.perf_counter()
    v, t = pytetwild.tetrahedralize(
        np.asarray(arrays["points"], np.float64), np.asarray(arrays["faces"], np.int32),
        edge_length_abs=float(opts["edge_length"]), epsilon=float(opts.get("epsilon", 1e-3)),
        optimize=True, num_threads=int(opts.get("threads", 1)), quiet=True,
        num_opt_iter=int(opts.get("num_opt_iter", 80)), stop_energy=float(opts.get("stop_energy", 10.0)),
    )
    return {"nodes": np.asarray(v, np.float64), "tets": np.asarray(t, np.int64)}, {"t_mesh": time.perf_counter() - t0}


_COMMANDS = {"read": _cmd_read, "mesh": _cmd_mesh, "tetwild": _cmd_tetwild}


def _main(folder: str) -> int:
    d = Path(folder)
    spec = json.loads((d / "in.json").read_text())
    with np.load(d / "in.npz") as z:
        arrays = {k: z[k] for k in z.files}
    log: list[str] = []
    try:
        out, info = _COMMANDS[spec["command"]](spec.get("options", {}), arrays)
        with contextlib.suppress(Exception):
            import gmsh

            if gmsh.isInitialized():
                log = list(gmsh.logger.get())
    except Exception as exc:  # report, never a traceback to the parent's user
        with contextlib.suppress(Exception):
            import gmsh

            if gmsh.isInitialized():
                log = list(gmsh.logger.get())
        msg = " ".join(str(exc).split()) or type(exc).__name__
        errors = [" ".join(ln.split()) for ln in log if ln.startswith("Error")]
        if errors:
            last = errors[-1].removeprefix("Error: ")
            if last not in " ".join(msg.split()):
                msg = f"{msg} ({last})"
        (d / "error.json").write_text(json.dumps({"error": msg, "log": log[-200:]}))
        return 1
    np.savez(d / "out.npz", **out)
    (d / "out.json").write_text(json.dumps({"info": info, "log": log[-200:]}))
    return 0


if __name__ == "__main__":  # pragma: no cover - runs in the child
    sys.exit(_main(sys.argv[1]))
