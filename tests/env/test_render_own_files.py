"""Pictures read only a bundle's own files. A bundle whose ``annotations.geojson`` is a symbolic
link to a file outside it is refused in one line naming the bundle and the entry, not followed."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from data_tools.errors import BundleError


def test_render_refuses_an_annotations_link_to_a_file_outside(tmp_path):
    import histojax
    from histojax.render import render_trajectory, tumour_rings
    from histojax.sample import sample_bundle

    bundle = shutil.copytree(sample_bundle(progress=False), tmp_path / "slide")
    env, _ = histojax.make("HistoJAX-Easy-v0", slide=str(bundle))
    z, x, y = np.zeros(2, np.int32), np.zeros(2, np.int32), np.zeros(2, np.int32)
    assert tumour_rings(env)  # the bundle's own outline is drawn
    render_trajectory(env, z, x, y)

    outside = tmp_path / "elsewhere.geojson"  # a valid GeoJSON: before, it was read and drawn as the tumour
    square = [[0, 0], [50, 0], [50, 50], [0, 50], [0, 0]]
    outside.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {"label": "tumour"},
                        "geometry": {"type": "Polygon", "coordinates": [square]},
                    }
                ],
            }
        )
    )
    (bundle / "annotations.geojson").unlink()
    (bundle / "annotations.geojson").symlink_to(outside)
    for draw in (lambda: tumour_rings(env), lambda: render_trajectory(env, z, x, y)):
        with pytest.raises(BundleError) as e:
            draw()
        line = str(e.value)
        assert "\n" not in line and str(bundle) in line and "'annotations.geojson'" in line
        assert "symbolic link" in line

    (bundle / "annotations.geojson").unlink()  # no annotations at all: nothing drawn, no error
    assert tumour_rings(env) == []
