"""Fixed regions: parsing the [fixed] table and selecting nodes."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.network.regions import FixedRegion, region_from_config, select_fixed
from esmm.pipeline.network.springs import NODE_INTERIOR, NODE_SURFACE


@pytest.fixture()
def bar():
    """Grid points of a 20 x 30 x 100 mm bar, rotated so that its long axis is not a mesh axis."""
    x, y, z = np.meshgrid(np.linspace(0, 0.02, 5), np.linspace(0, 0.03, 7), np.linspace(0, 0.1, 21),
                          indexing="ij")
    p = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    kind = np.where(np.any((p <= 1e-12) | (p >= np.array([0.02, 0.03, 0.1]) - 1e-12), axis=1),
                    NODE_SURFACE, NODE_INTERIOR).astype(np.uint8)
    return p, p @ rot.T, rot, kind


def test_default_band_is_the_low_end_of_the_longest_axis(bar):
    p, q, rot, _ = bar
    sel = select_fixed(q, region_from_config(None))
    # The longest axis is the bar's z (rotated); signed so its largest component is positive.
    axis = rot @ np.array([0, 0, 1.0])
    s = q @ axis
    z = p[:, 2] if axis[np.argmax(np.abs(axis))] > 0 else 0.1 - p[:, 2]
    expected = np.flatnonzero(z <= 0.01 + 1e-12)  # 10 % of 100 mm, rows at 0 and 5 mm and 10 mm
    assert np.array_equal(sel, expected)
    assert s[sel].max() <= s.min() + 0.01 + 1e-9
    sel_max = select_fixed(q, region_from_config({"kind": "band", "end": "max", "width_fraction": 0.05}))
    assert np.array_equal(sel_max, np.flatnonzero(z >= 0.095 - 1e-12))


def test_band_by_plane(bar):
    p, _, _, _ = bar
    r = region_from_config({"kind": "band", "axis": [0, 0, 2], "offset": "20 mm", "width": "10 mm"})
    sel = select_fixed(p, r)
    assert np.array_equal(sel, np.flatnonzero((p[:, 2] >= 0.02 - 1e-12) & (p[:, 2] <= 0.03 + 1e-12)))
    assert "band from 20 mm" in r.describe()
    again = region_from_config(r.to_config())
    assert np.array_equal(select_fixed(p, again), sel)


def test_box_nearest_none_and_surface_only(bar):
    p, _, _, kind = bar
    box = region_from_config({"kind": "box", "lower": ["-1 mm", "-1 mm", "-1 mm"], "upper": ["1 cm", "31 mm", "0.5 mm"]})
    sel = select_fixed(p, box)
    assert np.array_equal(sel, np.flatnonzero((p[:, 0] <= 0.01 + 1e-12) & (p[:, 2] <= 0.0005)))
    near = region_from_config({"kind": "nearest", "point": ["0 mm", "0 mm", "0 mm"], "count": 4})
    sel = select_fixed(p, near)
    d = np.linalg.norm(p, axis=1)
    assert sel.size == 4 and d[sel].max() <= np.sort(d)[3] + 1e-15 and 0 in sel
    assert select_fixed(p, region_from_config({"kind": "none"})).size == 0
    surf = region_from_config({"kind": "band", "axis": [0, 0, 1], "offset": "40 mm", "width": "1 mm",
                               "surface_only": True})
    sel = select_fixed(p, surf, node_kind=kind)
    assert sel.size and np.all(kind[sel] == NODE_SURFACE)
    assert sel.size < select_fixed(p, region_from_config({"kind": "band", "axis": [0, 0, 1], "offset": "40 mm",
                                                         "width": "1 mm"})).size


@pytest.mark.parametrize("table, match", [
    ({"kind": "disc"}, "kind"),
    ({"kind": "band", "thickness": "1 mm"}, "unknown key"),
    ({"kind": "band", "width": 10}, "has no unit"),
    ({"kind": "band", "width": "-1 mm"}, "positive"),
    ({"kind": "band", "width": "1 mm", "width_fraction": 0.1}, "not both"),
    ({"kind": "band", "width_fraction": 1.5}, "width_fraction"),
    ({"kind": "band", "axis": [0, 0, 0], "offset": "0 mm", "width": "1 mm"}, "zero vector"),
    ({"kind": "band", "axis": "x"}, "axis"),
    ({"kind": "band", "offset": "0 mm"}, "absolute width"),
    ({"kind": "band", "end": "top"}, "end"),
    ({"kind": "box", "lower": ["0 mm", "0 mm", "0 mm"]}, "upper"),
    ({"kind": "box", "lower": ["0 mm"] * 3, "upper": ["1 mm", "0 mm", "1 mm"]}, "exceed"),
    ({"kind": "nearest", "point": ["0 mm"] * 3, "count": 0}, "count"),
    ({"kind": "nearest", "point": [0, 0, 0], "count": 3}, "unit"),
    ({"kind": "band", "surface_only": "yes"}, "surface_only"),
])
def test_bad_tables_give_one_line_config_errors(table, match):
    with pytest.raises(ConfigError, match=match) as info:
        region_from_config(table)
    assert "\n" not in str(info.value) and "[fixed]" in str(info.value)


def test_empty_selection_is_an_error(bar):
    p, _, _, _ = bar
    far = region_from_config({"kind": "box", "lower": ["1 m", "1 m", "1 m"], "upper": ["2 m", "2 m", "2 m"]})
    with pytest.raises(ConfigError, match="holds no node.*bounding box"):
        select_fixed(p, far)
    band = region_from_config({"kind": "band", "axis": [1, 0, 0], "offset": "500 mm", "width": "1 mm"})
    with pytest.raises(ConfigError, match="holds no node"):
        select_fixed(p, band)
    with pytest.raises(ConfigError, match="only"):
        select_fixed(p, FixedRegion(kind="nearest", point=np.zeros(3), count=10**6))
