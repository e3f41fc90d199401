"""Off-screen video of a simulation history (pyvista/VTK, no display, no GPU).

The organ's surface is drawn coloured by the displacement magnitude [mm]
(fixed colour range: 0 to the largest displacement of the run, with a scalar
bar), the fixed nodes as dark points, the grasper as a sphere at its tip with
a shaft along the outward surface normal of the grasped point, and the
simulated time (and the grasper force) as text. The camera is fitted once to
the bounding box of every frame, so the organ never leaves the picture. One
video frame per history frame, played at the scene's frame rate: the video
runs in simulated real time.

Rendering needs an OpenGL context without a display. On Linux without
``DISPLAY`` we ask VTK for its EGL render window (works with Mesa's llvmpipe
software renderer: no GPU needed); VTK wheels built with OSMesa work too.
Anti-aliasing is off (MSAA is slow in software and not reproducible).
Frames are encoded with the ffmpeg binary of the imageio-ffmpeg wheel (H.264,
yuv420p) into a temporary file renamed on success.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from ..atomicio import atomic_path
from ..errors import EsmmError
from ..progress import ensure
from .history import History
from .scene import VideoSpec


class RenderError(EsmmError):
    """Off-screen rendering or video encoding is not available here."""

    exit_code = 3


def _prepare_offscreen() -> None:
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        # Without this VTK first tries X11, logs "bad X server connection", then falls back to EGL.
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _pyvista():
    _prepare_offscreen()
    try:
        import pyvista as pv
    except ImportError as exc:  # pragma: no cover - a dependency
        raise RenderError(f"pyvista is not installed ({exc}); reinstall esmm with its dependencies") from None
    pv.OFF_SCREEN = True
    return pv


def auto_view(points: np.ndarray, motion: np.ndarray, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera direction (from the focal point to the camera) and up vector for view "auto".

    Look across the dominant motion (so it shows in the picture plane), as close
    as possible to the organ's thinnest principal axis (so the organ looks
    large), tilted 25 degrees towards "up" (against gravity) for depth; "up" is
    against gravity when that is not along the line of sight.
    """
    p = np.asarray(points, dtype=np.float64)
    p = p - p.mean(axis=0)
    _, _, vt = np.linalg.svd(p[:: max(1, p.shape[0] // 20000)], full_matrices=False)
    m = np.asarray(motion, dtype=np.float64)
    mn = float(np.linalg.norm(m))
    look = vt[2].copy()
    if mn > 0:
        m = m / mn
        for cand in (vt[2], vt[1], vt[0]):
            q = cand - m * (cand @ m)
            if np.linalg.norm(q) > 0.3:
                look = q / np.linalg.norm(q)
                break
    g = np.asarray(gravity, dtype=np.float64)
    up = -g if np.linalg.norm(g) > 0 else (m if mn > 0 else vt[1])
    up = up - look * (up @ look)
    if np.linalg.norm(up) < 1e-6:
        up = vt[1] - look * (vt[1] @ look)
    up = up / np.linalg.norm(up)
    tilt = np.deg2rad(25.0)
    look2 = np.cos(tilt) * look + np.sin(tilt) * up
    up2 = -np.sin(tilt) * look + np.cos(tilt) * up
    return look2 / np.linalg.norm(look2), up2 / np.linalg.norm(up2)


def _attr_vector(attrs, key, default) -> np.ndarray:
    """A 3-vector attribute of a history (stored as JSON text or as an array)."""
    v = attrs.get(key, None)
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, str):
        import json

        try:
            v = json.loads(v)
        except ValueError:
            v = None
    try:
        out = np.asarray(default if v is None else v, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        out = np.asarray(default, dtype=np.float64)
    return out if np.all(np.isfinite(out)) else np.asarray(default, dtype=np.float64)


class FrameRenderer:
    """Draw the frames of a :class:`History` off-screen.

    Parameters
    ----------
    history : History
    video : VideoSpec
    forces : bool
        Print the grasper force magnitude (interpolated at the frame time).
    """

    def __init__(self, history: History, video: VideoSpec | None = None, *, forces: bool = True):
        pv = _pyvista()
        video = VideoSpec() if video is None else video
        self.h = history
        self.video = video
        rest = history.points
        faces = history.surface
        if faces.size == 0:
            raise RenderError(f"{history.path}: the history has no surface triangles to draw")
        used = np.unique(faces)
        self._used = used
        remap = np.full(rest.shape[0], -1, np.int64)
        remap[used] = np.arange(used.size)
        tri = remap[faces]
        cells = np.hstack([np.full((tri.shape[0], 1), 3), tri]).ravel()
        self.mesh = pv.PolyData(rest[used].copy(), cells)
        self.mesh.point_data["|u| [mm]"] = np.zeros(used.size)
        self.umax_mm = max(history.max_displacement() * 1e3, 1e-6)
        size = float(np.linalg.norm(np.ptp(rest, axis=0)))
        self.size = size
        try:
            self.pl = pv.Plotter(off_screen=True, window_size=(video.width, video.height))
        except Exception as exc:  # VTK raises plain RuntimeErrors here
            raise RenderError(f"cannot open an off-screen OpenGL context ({exc}); install Mesa's EGL "
                              "(libegl1) or the vtk-osmesa wheel") from None
        pl = self.pl
        try:
            pl.disable_anti_aliasing()
        except Exception:
            pass
        pl.set_background("white")
        fs = max(6, int(round(video.height / 48)))
        pl.add_mesh(self.mesh, scalars="|u| [mm]", cmap=video.colormap, clim=(0.0, self.umax_mm),
                    show_edges=video.show_edges, edge_color="gray", smooth_shading=True,
                    scalar_bar_args=dict(title="|u| [mm]", vertical=True, position_x=0.87,
                                         position_y=0.25, height=0.55, width=0.05, color="black",
                                         fmt="%.1f", title_font_size=fs, label_font_size=fs))
        self.fixed_cloud = None
        fixed_vis = np.intersect1d(history.fixed, used)
        if video.show_fixed and fixed_vis.size:
            self._fixed_idx = fixed_vis
            self.fixed_cloud = pv.PolyData(rest[fixed_vis].copy())
            pl.add_mesh(self.fixed_cloud, color="#303030", point_size=max(2.0, video.height / 240),
                        render_points_as_spheres=False)
        # The grasper: a sphere at the tip and a shaft along the outward normal.
        normal = _attr_vector(history.attrs, "grasper_normal", (0.0, 0.0, 1.0))
        self.normal = normal / (np.linalg.norm(normal) or 1.0)
        r = 0.02 * size
        self.tip_actor = pl.add_mesh(pv.Sphere(radius=r, center=(0, 0, 0)), color="#c0c0c0",
                                     smooth_shading=True)
        shaft_len = 0.35 * size
        shaft = pv.Cylinder(center=self.normal * (shaft_len / 2 + r * 0.5), direction=self.normal,
                            radius=0.35 * r, height=shaft_len)
        self.shaft_actor = pl.add_mesh(shaft, color="#808080", smooth_shading=True)
        self._set_grasper(None)
        self.text = pl.add_text("", position="upper_left", font_size=fs, color="black")
        self._ft, self._ff = history.forces() if forces else (np.zeros(0), np.zeros((0, 3)))
        self._fit_camera()

    # -- scene pieces ------------------------------------------------------
    def _set_grasper(self, tip) -> None:
        visible = tip is not None and np.all(np.isfinite(tip))
        for a in (self.tip_actor, self.shaft_actor):
            a.SetVisibility(bool(visible))
            if visible:
                a.SetPosition(*np.asarray(tip, dtype=float))

    def _fit_camera(self) -> None:
        h = self.h
        lo = h.points.min(axis=0)
        hi = h.points.max(axis=0)
        for k in range(h.n_frames):
            p = h.points + h.displacement(k)
            lo = np.minimum(lo, p.min(axis=0))
            hi = np.maximum(hi, p.max(axis=0))
        # The dominant motion: displacement of the node that moves most, at its largest.
        motion = np.zeros(3)
        for k in range(h.n_frames):
            u = h.displacement(k)
            a = int(np.argmax(np.einsum("ij,ij->i", u, u)))
            if u[a] @ u[a] > motion @ motion:
                motion = u[a].copy()
        tips = h.tips[np.all(np.isfinite(h.tips), axis=1)]
        if tips.size:
            lo = np.minimum(lo, tips.min(axis=0))
            hi = np.maximum(hi, tips.max(axis=0))
        bounds = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
        pl = self.pl
        view = self.video.view
        if view == "xy":
            pl.view_xy()
        elif view == "xz":
            pl.view_xz()
        elif view == "yz":
            pl.view_yz()
        elif view == "iso":
            pl.view_isometric()
        else:
            look, up = auto_view(h.points, motion, _attr_vector(h.attrs, "gravity", (0.0, 0.0, -1.0)))
            c = 0.5 * (lo + hi)
            cam = pl.camera
            cam.focal_point = tuple(c)
            cam.position = tuple(c + look * 3.0 * self.size)
            cam.up = tuple(up)
        pl.reset_camera(bounds=bounds)
        if self.video.zoom != 1.0:
            pl.camera.zoom(self.video.zoom)

    # -- frames ----------------------------------------------------------------
    def frame(self, k: int) -> np.ndarray:
        """Render history frame *k*; returns an RGB image (height, width, 3) uint8."""
        h = self.h
        u = h.displacement(k)
        p = h.points + u
        self.mesh.points[:] = p[self._used]
        self.mesh.point_data["|u| [mm]"][:] = np.linalg.norm(u[self._used], axis=1) * 1e3
        self.mesh.Modified()
        if self.fixed_cloud is not None:
            self.fixed_cloud.points[:] = p[self._fixed_idx]
            self.fixed_cloud.Modified()
        tip = h.tips[k]
        self._set_grasper(tip if np.all(np.isfinite(tip)) else None)
        t = float(h.times[k])
        label = f"t = {t:6.3f} s"
        if self._ft.size:
            j = int(np.clip(np.searchsorted(self._ft, t), 0, self._ft.size - 1))
            if np.all(np.isfinite(tip)):
                label += f"\nF = {np.linalg.norm(self._ff[j]):.3g} N"
        self.text.SetText(2, label)
        self.pl.render()
        img = self.pl.screenshot(return_img=True)
        return np.ascontiguousarray(img[:, :, :3])

    def close(self) -> None:
        self.pl.close()

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_video(history, out_path, *, video: VideoSpec | None = None, fps: float | None = None,
                 reporter=None) -> dict:
    """Render every frame of *history* into an H.264 video at *out_path*.

    Parameters
    ----------
    history : History or path-like
    out_path : path-like
        ``.mp4`` (or another container ffmpeg knows by extension).
    video : VideoSpec
    fps : float, optional
        Frames per second of the video; default: the history's frame rate
        (the video then runs in simulated real time).

    Returns
    -------
    dict with ``frames``, ``seconds`` (wall time), ``render_fps``, ``path``.
    """
    rep = ensure(reporter)
    video = VideoSpec() if video is None else video
    own = not isinstance(history, History)
    h = History(history) if own else history
    try:
        import imageio_ffmpeg
    except ImportError as exc:  # pragma: no cover - a dependency
        raise RenderError(f"imageio-ffmpeg is not installed ({exc}); reinstall esmm") from None
    if fps is None:
        fps = float(h.attrs.get("frame_rate", 30.0))
    t0 = time.perf_counter()
    try:
        with FrameRenderer(h, video) as fr, atomic_path(out_path) as tmp:
            writer = imageio_ffmpeg.write_frames(str(tmp), (video.width, video.height), fps=fps,
                                                 codec="libx264", pix_fmt_out="yuv420p", quality=7,
                                                 macro_block_size=2, ffmpeg_log_level="error")
            writer.send(None)
            try:
                with rep.task("rendering video", total=h.n_frames) as advance:
                    for k in range(h.n_frames):
                        writer.send(fr.frame(k))
                        advance(1)
            finally:
                writer.close()
    except (OSError, RuntimeError) as exc:
        raise RenderError(f"{out_path}: video encoding failed ({exc}); check the folder is writable "
                          "and has space") from None
    finally:
        if own:
            h.close()
    sec = time.perf_counter() - t0
    n = h.n_frames
    return {"frames": n, "seconds": sec, "render_fps": n / sec if sec > 0 else float("inf"),
            "path": str(out_path)}
