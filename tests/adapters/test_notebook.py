"""examples/quickstart.ipynb runs top to bottom (nbclient, the ``test`` extra): make, step, vmap, a small PPO,
evaluation, the pictures. About a minute of CPU: marked slow (``make test-all``)."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = ROOT / "examples" / "quickstart.ipynb"


@pytest.mark.slow
def test_quickstart_notebook_runs_and_shows_what_it_says():
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")

    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code")  # shipped without outputs
    nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    ).execute()
    text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "env steps/s with 128 envs" in text
    assert "colour-stats features, 8 numbers per view" in text
    assert "PPO     success" in text and "random  success" in text
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]
    assert images, "the path (and the reading map, when histojax.render has it) are drawn"


def test_quickstart_notebook_is_valid_and_lists_its_steps():
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    source = "\n".join(c.source for c in nb.cells)
    for step in ("histojax.make", "jax.vmap", "ppo.make_train", "run_episodes", "render_reading_map"):
        assert step in source, step
