"""One import path per name: the old alias modules are gone, and nothing in the repository names them."""
import importlib.util
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

# old path -> the one path of the same names
GONE = {
    "data_tools.c16": "data_tools.datasets.c16",
    "data_tools.c16_layout": "data_tools.datasets.c16_layout",
    "data_tools.c16_mosaic": "data_tools.datasets.c16_mosaic",
    "data_tools.pcam_bank": "data_tools.datasets.pcam_bank",
    "data_tools.synth": "data_tools.datasets.synth",
    "data_tools.synth_large": "data_tools.datasets.synth_large",
    "histojax.compat": "histojax.adapters.histogym",
    "histojax.gymnasium_bridge": "histojax.adapters.gymnasium",
    "histojax.sb3": "histojax.adapters.sb3",
    "histojax.wrappers": "histojax.adapters.jax",
    # the reading stack, one package (histojax.reading) and its baselines (baselines.reading)
    "histojax.modes": "histojax.core.modes.base",
    "histojax.glimpse": "histojax.reading.modes.glimpse",
    "histojax.zoom_select": "histojax.reading.modes.zoom_select",
    "histojax.mode_registry": "histojax.core.modes.factory",
    "histojax.coarse_map": "histojax.reading.coarse_map",
    "histojax.head": "histojax.reading.heads",
    "histojax.head_mil": "histojax.reading.heads.mil",
    "histojax.head_reward": "histojax.reading.head_reward",
    # the env core on its own floor (histojax.core), the head reward with the reading stack
    "histojax.reading.modes.base": "histojax.core.modes.base",
    "histojax.reading.modes.factory": "histojax.core.modes.factory",
    "histojax.adapters.head_reward": "histojax.reading.head_reward",
    "histojax.env": "histojax.core.env",
    "histojax.actions": "histojax.core.actions",
    "histojax.views": "histojax.core.views",
    "histojax.rewards": "histojax.core.rewards",
    "histojax.augment": "histojax.core.augment",
    "histojax.slide": "histojax.core.slide",
    "histojax.spaces": "histojax.core.spaces",
    "histojax.gymnax_classes": "histojax.core.gymnax_classes",
    "baselines.head_fit": "baselines.reading.head_fit",
    "baselines.head_mil_fit": "baselines.reading.head_mil_fit",
    "baselines.readers": "baselines.reading.readers",
    "baselines.budget_curve": "baselines.reading.budget_curve",
    "baselines.head_diagnosis": "baselines.reading.diagnosis",
    "baselines.mil": "histojax.reading.heads.mil",
    "benchmarks.train_readers": "baselines.reading.train_readers",
    # experiment drivers: benchmarks/ measures speed and memory only
    "benchmarks.annotation_cost": "experiments.annotation_cost",
    "benchmarks.c16_patch_record": "experiments.c16_patch_record",
    "benchmarks.c16_reference": "experiments.c16_reference",
    "benchmarks.c16_sanity": "experiments.c16_sanity",
    "benchmarks.c16_slide_ceiling": "experiments.c16_slide_ceiling",
    "benchmarks.checkpoint_to_run": "experiments.checkpoint_to_run",
    "benchmarks.encoder_patches": "experiments.encoder_patches",
    "benchmarks.heldout_targets": "experiments.heldout_targets",
    "benchmarks.integrations_learning": "experiments.integrations_learning",
    "benchmarks.navigator_ceiling": "experiments.navigator_ceiling",
}


@pytest.mark.parametrize("old, new", sorted(GONE.items()))
def test_old_path_is_gone(old, new):
    assert importlib.util.find_spec(old) is None, f"{old} still importable; the one path is {new}"
    assert importlib.util.find_spec(new) is not None


def test_nothing_names_an_old_path():
    """Code, tests, docs, examples and the Makefile use only the one path of each name."""
    pattern = re.compile(r"\b(" + "|".join(re.escape(o) for o in GONE) + r")\b")
    files = [p for d in ("histojax", "data_tools", "baselines", "benchmarks", "experiments", "examples", "tests", "docs")
             if (ROOT / d).is_dir() for p in (ROOT / d).rglob("*")
             if p.suffix in (".py", ".md", ".ipynb", ".toml", ".cfg", ".txt") and p.name != "test_import_paths.py"]
    files += [ROOT / n for n in ("README.md", "Makefile", "pyproject.toml") if (ROOT / n).is_file()]
    hits = []
    for path in files:
        for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for m in pattern.finditer(line):
                hits.append(f"{path.relative_to(ROOT)}:{lineno}: {m.group(1)}")
    assert not hits, "old import paths still named:\n" + "\n".join(hits)
