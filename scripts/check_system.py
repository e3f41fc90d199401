"""Check that the system libraries behind gmsh and VTK are present.

gmsh's PyPI wheel links libGLU and a few X libraries even when no window is
opened; VTK's off-screen rendering needs Mesa's EGL or OSMesa. When one is
missing this prints exactly which Debian/Ubuntu packages provide it.
"""

from __future__ import annotations

import ctypes.util
import sys

NEEDED = {
    # library soname stem: (who needs it, Debian package)
    "GLU": ("gmsh", "libglu1-mesa"),
    "Xcursor": ("gmsh", "libxcursor1"),
    "Xft": ("gmsh", "libxft2"),
    "Xinerama": ("gmsh", "libxinerama1"),
    "fontconfig": ("gmsh", "libfontconfig1"),
    "Xrender": ("gmsh, vtk", "libxrender1"),
    "GL": ("vtk", "libgl1"),
    "EGL": ("vtk off-screen", "libegl1"),
}


def main() -> int:
    missing = [(lib, who, pkg) for lib, (who, pkg) in NEEDED.items() if ctypes.util.find_library(lib) is None]
    if missing:
        pkgs = " ".join(sorted({pkg for _, _, pkg in missing}))
        for lib, who, pkg in missing:
            print(f"missing system library lib{lib} (needed by {who}; Debian package {pkg})", file=sys.stderr)
        print(f"install them with:  sudo apt-get update && sudo apt-get install -y {pkgs}", file=sys.stderr)
        return 1
    try:
        import gmsh  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the machine
        print(f"gmsh does not load: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
