"""Off-screen video of a simulation history (pyvista/VTK, no display, no GPU).

The organ's surface is drawn coloured by its motion since the first frame
[mm] (the scene's start; fixed colour range: 0 to the largest over the run,
with a scalar bar), the fixed nodes as dark points, the grasper as a sphere at its tip with
a shaft (between the outward surface normal and the pull direction), and the
simulated time (and the grasper force) as text. View "auto" looks
horizontally with the view-up against gravity (:func:`auto_view`), and the
camera is fitted once to every frame (:func:`fit_camera`), so the organ never
leaves the picture. One
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

import json
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


def auto_view(points: np.ndarray, motion: np.ndarray, gravity: np.ndarray, *,
              toward: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera direction (from the focal point to the camera) and view-up for view "auto".

    With gravity: the view-up is exactly against gravity (the organ is seen as it
    lies, a lift goes up on the screen) and the camera looks horizontally, along
    the organ's *thinnest horizontal* principal axis (second axis of the
    footprint on the horizontal plane), so its widest horizontal extent spans
    the picture. If the dominant motion's horizontal part points mostly along
    that line of sight (it would be seen end-on), the camera looks along the
    widest horizontal axis instead. Of the two sides, the camera is on the side
    of *toward* (the grasped point), so the instrument faces it.

    Without gravity: across the dominant motion, as close as possible to the
    organ's thinnest principal axis, tilted 25 degrees towards the motion.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    motion : ndarray, shape (3,)
        The run's dominant displacement (may be zero).
    gravity : ndarray, shape (3,)
    toward : ndarray, shape (3,), optional
        A point the camera should face (the grasped point).

    Returns
    -------
    (look, up) : unit ndarrays, shape (3,), orthogonal.
    """
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    p = p - c
    sample = p[:: max(1, p.shape[0] // 20000)]
    m = np.asarray(motion, dtype=np.float64)
    mn = float(np.linalg.norm(m))
    g = np.asarray(gravity, dtype=np.float64)
    gn = float(np.linalg.norm(g))
    if gn > 0:
        up = -g / gn
        # an orthonormal basis of the horizontal plane, then the footprint's principal axes
        a = np.eye(3)[int(np.argmin(np.abs(up)))]
        h1 = a - up * (a @ up)
        h1 /= np.linalg.norm(h1)
        h2 = np.cross(up, h1)
        xy = sample @ np.stack([h1, h2], axis=1)                  # (k, 2) horizontal coordinates
        _, _, vt = np.linalg.svd(xy - xy.mean(axis=0), full_matrices=False)
        wide = vt[0, 0] * h1 + vt[0, 1] * h2
        thin = vt[1, 0] * h1 + vt[1, 1] * h2
        look = thin
        if mn > 0:
            mh = m - up * (m @ up)
            if np.linalg.norm(mh) > 0.5 * mn and abs(mh @ thin) > 0.7 * np.linalg.norm(mh):
                look = wide
        side = 0.0 if toward is None else float((np.asarray(toward, dtype=np.float64) - c) @ look)
        if side < 0 or (side == 0 and look @ np.ones(3) < 0):
            look = -look
        return look / np.linalg.norm(look), up
    _, _, vt = np.linalg.svd(sample, full_matrices=False)
    look = vt[2].copy()
    if mn > 0:
        mu = m / mn
        for cand in (vt[2], vt[1], vt[0]):
            q = cand - mu * (cand @ mu)
            if np.linalg.norm(q) > 0.3:
                look = q / np.linalg.norm(q)
                break
    up = m / mn if mn > 0 else vt[1]
    up = up - look * (up @ look)
    if np.linalg.norm(up) < 1e-6:
        up = vt[1] - look * (vt[1] @ look)
    up = up / np.linalg.norm(up)
    tilt = np.deg2rad(25.0)
    look2 = np.cos(tilt) * look + np.sin(tilt) * up
    up2 = -np.sin(tilt) * look + np.cos(tilt) * up
    return look2 / np.linalg.norm(look2), up2 / np.linalg.norm(up2)


#: Part of the picture the organ is fitted into (fractions of width and height from the
#: lower left): the scalar bar sits on the right, the time and force labels at the top left.
FIT_BOX = (0.03, 0.83, 0.04, 0.86)
#: The colour field: motion since the first frame [mm].
SCALARS = "moved [mm]"


def fit_camera(look: np.ndarray, up: np.ndarray, frames_points, *, view_angle_deg: float = 30.0,
               aspect: float = 4 / 3, box=FIT_BOX) -> tuple[np.ndarray, np.ndarray]:
    """Perspective camera (position, focal point) along *look* that keeps every frame in *box*.

    The points of every frame are expressed in the camera's basis (right,
    up, toward the camera); the camera distance is the smallest for which the
    nearest extreme points stay inside the box's angular extent, and the camera
    is shifted sideways so that the box's centre is the points' centre.

    Parameters
    ----------
    look, up : ndarray, shape (3,)
        Unit direction from the focal point to the camera, and view-up (orthogonal).
    frames_points : iterable of ndarray, shape (n, 3)
        The positions to keep in view (each frame, the grasper tip path).
    view_angle_deg : float
        Vertical view angle (VTK's default 30).
    aspect : float
        Width / height of the picture.
    box : (x0, x1, y0, y1)
        Fractions of the picture.

    Returns
    -------
    (position, focal_point) : ndarray, shape (3,)
    """
    look = np.asarray(look, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(up, look)            # VTK: right = direction_of_projection x up = -look x up
    basis = np.stack([right, up, look], axis=1)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for pts in frames_points:
        q = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        if q.size == 0:
            continue
        q = q[np.all(np.isfinite(q), axis=1)] @ basis
        if q.size:
            lo = np.minimum(lo, q.min(axis=0))
            hi = np.maximum(hi, q.max(axis=0))
    if not np.all(np.isfinite(lo)):
        lo, hi = -np.ones(3), np.ones(3)
    size = max(float((hi - lo).max()), 1e-9)
    hi = np.maximum(hi, lo + 1e-6 * size)
    tv = np.tan(np.deg2rad(view_angle_deg) / 2)
    th = tv * aspect
    x0, x1, y0, y1 = box
    # normalised screen coordinates of the box: [-1, 1] spans the picture
    bx0, bx1, by0, by1 = 2 * x0 - 1, 2 * x1 - 1, 2 * y0 - 1, 2 * y1 - 1
    cx, cy = 0.5 * (lo[:2] + hi[:2])
    half_r, half_u = 0.5 * (hi[:2] - lo[:2])
    mid = 0.5 * (lo[2] + hi[2])
    # the points nearest to the camera constrain most: distance from the camera at depth D is D - depth
    dist = hi[2] + max(half_r / (0.5 * (bx1 - bx0) * th), half_u / (0.5 * (by1 - by0) * tv))
    # sideways shift: the points' centre lands on the box's centre (exact at the middle depth)
    camx = cx - 0.5 * (bx0 + bx1) * th * (dist - mid)
    camy = cy - 0.5 * (by0 + by1) * tv * (dist - mid)
    position = basis @ np.array([camx, camy, dist])
    focal = basis @ np.array([camx, camy, mid])
    return position, focal


def _attr_vector(attrs, key, default) -> np.ndarray:
    """A 3-vector attribute of a history (stored as JSON text or as an array)."""
    v = attrs.get(key, None)
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, str):
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
        # Colour: the motion since the first frame (the scene's start, e.g. the equilibrium under
        # gravity), so that the grasper's action is not drowned by the initial sag.
        self.u0 = history.displacement(0) if history.n_frames else np.zeros_like(rest)
        self.mesh.point_data[SCALARS] = np.zeros(used.size)
        self.umax_mm = max(self._max_motion() * 1e3, 1e-6)
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
        pl.add_mesh(self.mesh, scalars=SCALARS, cmap=video.colormap, clim=(0.0, self.umax_mm),
                    show_edges=video.show_edges, edge_color="gray", smooth_shading=True,
                    scalar_bar_args=dict(title=SCALARS, vertical=True, position_x=0.87,
                                         position_y=0.25, height=0.55, width=0.05, color="black",
                                         fmt="%.1f", title_font_size=fs, label_font_size=fs))
        self.fixed_cloud = None
        fixed_vis = np.intersect1d(history.fixed, used)
        if video.show_fixed and fixed_vis.size:
            self._fixed_idx = fixed_vis
            self.fixed_cloud = pv.PolyData(rest[fixed_vis].copy())
            pl.add_mesh(self.fixed_cloud, color="#303030", point_size=max(2.0, video.height / 240),
                        render_points_as_spheres=False)
        # The grasper: a sphere at the tip and a shaft, the instrument's axis: halfway between the
        # outward normal of the grasped point and the pull direction (an instrument pulling along
        # its axis, never through the organ); the normal alone when the two are opposite.
        normal = _attr_vector(history.attrs, "grasper_normal", (0.0, 0.0, 1.0))
        normal = normal / (np.linalg.norm(normal) or 1.0)
        pull = _attr_vector(history.attrs, "grasper_direction", (0.0, 0.0, 0.0))
        pull = pull / (np.linalg.norm(pull) or 1.0)
        axis = normal + pull
        self.normal = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0.2 else normal
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

    def _max_motion(self) -> float:
        """Largest displacement from the first frame over all frames [m]."""
        h = self.h
        return max((float(np.linalg.norm(h.displacement(k) - self.u0, axis=1).max())
                    for k in range(h.n_frames)), default=0.0)

    # -- scene pieces ------------------------------------------------------
    def _set_grasper(self, tip) -> None:
        visible = tip is not None and np.all(np.isfinite(tip))
        for a in (self.tip_actor, self.shaft_actor):
            a.SetVisibility(bool(visible))
            if visible:
                a.SetPosition(*np.asarray(tip, dtype=float))

    def _fit_camera(self) -> None:
        h = self.h
        # The dominant motion: displacement of the node that moves most, at its largest.
        motion = np.zeros(3)
        frames = []
        for k in range(h.n_frames):
            u = h.displacement(k)
            a = int(np.argmax(np.einsum("ij,ij->i", u, u)))
            if u[a] @ u[a] > motion @ motion:
                motion = u[a].copy()
            frames.append(h.points[self._used] + u[self._used])
        tips = h.tips[np.all(np.isfinite(h.tips), axis=1)]
        if tips.size:
            frames.append(tips)
        pl = self.pl
        view = self.video.view
        if view in ("xy", "xz", "yz", "iso"):
            frames = frames or [h.points]
            lo = np.min([f.min(axis=0) for f in frames], axis=0)
            hi = np.max([f.max(axis=0) for f in frames], axis=0)
            {"xy": pl.view_xy, "xz": pl.view_xz, "yz": pl.view_yz, "iso": pl.view_isometric}[view]()
            pl.reset_camera(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        else:
            target = h.attrs.get("grasper_target", None)
            toward = None
            if target is not None and 0 <= int(target) < h.points.shape[0]:
                toward = h.points[int(target)]
            elif tips.size:
                toward = tips[0]
            look, up = auto_view(h.points, motion, _attr_vector(h.attrs, "gravity", (0.0, 0.0, -1.0)),
                                 toward=toward)
            cam = pl.camera
            angle = float(cam.view_angle)
            pos, focal = fit_camera(look, up, frames, view_angle_deg=angle,
                                    aspect=self.video.width / self.video.height)
            cam.focal_point = tuple(focal)
            cam.position = tuple(pos)
            cam.up = tuple(up)
            pl.renderer.ResetCameraClippingRange()
        if self.video.zoom != 1.0:
            pl.camera.zoom(self.video.zoom)

    # -- frames ----------------------------------------------------------------
    def frame(self, k: int) -> np.ndarray:
        """Render history frame *k*; returns an RGB image (height, width, 3) uint8."""
        h = self.h
        u = h.displacement(k)
        p = h.points + u
        self.mesh.points[:] = p[self._used]
        self.mesh.point_data[SCALARS][:] = np.linalg.norm((u - self.u0)[self._used], axis=1) * 1e3
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
