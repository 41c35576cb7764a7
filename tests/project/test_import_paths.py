"""One import path per name: the old alias modules are gone, and nothing in the repository names them."""

import ast
import importlib.util
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]

# old path -> the one path of the same names
GONE = {
    "data_tools.c16": "data_tools.datasets.c16.dataset",
    "data_tools.c16_layout": "data_tools.datasets.c16.layout",
    "data_tools.c16_mosaic": "data_tools.datasets.c16.mosaic",
    "data_tools.pcam_bank": "data_tools.datasets.pcam_bank",
    "data_tools.synth": "data_tools.datasets.synth.dataset",
    "data_tools.synth_large": "data_tools.datasets.synth.large_slide",
    "data_tools.datasets.synth_large": "data_tools.datasets.synth.large_slide",
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
    # the run machinery in one harness package
    "baselines.common.cli": "baselines.harness.cli",
    "baselines.common.run_folder": "baselines.harness.run_folder",
    "baselines.common.runner": "baselines.harness.runner",
    "baselines.common.logs": "baselines.harness.logs",
    "baselines.curves": "baselines.harness.curves",
    "baselines.distributed": "baselines.harness.distributed",
    # small leaf modules folded into their users
    "baselines.reading.budgets": "baselines.reading.pipeline",
    "baselines.reading.lesions": "baselines.reading.slides",
    # slide-file readers under one name ("reader" elsewhere is a reading policy)
    "data_tools.slides": "data_tools.slide_files.tiff",
    "data_tools.slide_readers": "data_tools.slide_files.open",
    "data_tools.dicom": "data_tools.slide_files.dicom",
    "data_tools.openslide_reader": "data_tools.slide_files.openslide",
    "data_tools.mirax": "data_tools.slide_files.mirax",
    "data_tools.slide_limits": "data_tools.slide_files.limits",
    # the bundle format split along its sections: format (names, geometry, typed metadata, checksums), writes,
    # seals, safe_files, reading (the verified read); drop_pixels moved to the writer, data_tools.bundle
    "data_tools.bundle_format": "data_tools.bundle_files.format",
    # the CAMELYON16 benchmark's modules, one subpackage
    "data_tools.datasets.c16_inputs": "data_tools.datasets.c16.inputs",
    "data_tools.datasets.c16_layout": "data_tools.datasets.c16.layout",
    "data_tools.datasets.c16_mosaic": "data_tools.datasets.c16.mosaic",
    # a policy's episodes: a floor under evaluate and reading, which both run them
    "baselines.evaluate.policies": "baselines.episodes.policies",
    "baselines.evaluate.rollout": "baselines.episodes.rollout",
}

# names that left a module which still exists: old module -> (the one module of the names, the names)
MOVED_NAMES = {
    "baselines.common": (
        "their defining module (baselines.common.config / env / devices, baselines.harness.*)",
        (
            "make_env",
            "episode_stats",
            "reset_envs",
            "params_initialiser",
            "EnvConfig",
            "ConfigError",
            "batch_mesh",
            "shard_batch",
            "Progress",
            "report",
            "save_checkpoint",
            "load_checkpoint",
            "seeds_runner",
            "run_chunked",
            "run_and_save",
            "load_runner",
            "trainer_command",
            "parse_args",
            "config_from_args",
            "plot_curves",
            "HistojaxDataError",
        ),
    ),
    "baselines.reading.head_fit": (
        "baselines.reading.slides (loaders), baselines.reading.fitting (fit rules)",
        (
            "read_spec",
            "scale_warning",
            "warn_scale",
            "read_bundle",
            "finest_views",
            "load_slide",
            "load_slides",
            "split_bundles",
            "_label",
            "logistic_fit",
            "check_classes",
            "check_head",
            "MIN_SLIDES_PER_CLASS",
        ),
    ),
    "baselines.evaluate": (
        "their defining module (baselines.evaluate.checks / cli / heads / pictures / scoring, baselines.episodes.*)",
        (
            "RETIRED",
            "SET_READER",
            "check_config",
            "check_params_tree",
            "grid_refusal",
            "head_reward_settings",
            "known_config_keys",
            "provenance_warnings",
            "published_path",
            "refuse_not_an_agent",
            "resolve_head",
            "split_warnings",
            "add_arguments",
            "default_out",
            "main",
            "print_table",
            "resolve_slides",
            "run",
            "with_dataset",
            "head_env",
            "head_scored",
            "lesion_classes",
            "write_pictures",
            "diagnosis_actions",
            "learned_policy",
            "map_follower_policy",
            "network_for",
            "scripted_features_policy",
            "scripted_policy",
            "seeds_policy",
            "stain_offset",
            "check_fits",
            "episode_labels",
            "eval_env",
            "per_episode_params",
            "run_episodes",
            "summarise",
            "trajectory",
            "evaluate",
        ),
    ),
    "baselines.evaluate.checks": (
        "data_tools.metrics (UNDEFINED), baselines.run_config (known_config_keys)",
        ("UNDEFINED", "known_config_keys"),
    ),
    "baselines.reading.readers": (
        "baselines.reading.reader_scores (the library of the readers command, the diagnosis and the budget curve)",
        (
            "KINDS",
            "tumour_views",
            "cell_table",
            "masks_from_instances",
            "policy_masks",
            "padded_terms",
            "terms_scores",
            "head_scores",
            "overview_scores",
            "new_results",
            "add_reader",
            "score_reader_name",
            "unreadable_line",
            "scripted_results",
            "rows_from_results",
            "csv_rows",
            "cells_words",
            "load_split",
            "print_tables",
        ),
    ),
    "histojax.reading.heads.logit": ("the same module, named for what it is: LogitHead", ("SlideHead",)),
    "baselines.networks": (
        "baselines.cell_set_networks",
        (
            "EpisodeTables",
            "CellEncoder",
            "CellSetActorCritic",
            "RecurrentCellSetActorCritic",
            "uses_cell_sets",
            "NEG",
            "CELL_CHUNK",
            "SplitDense",
            "cell_layers",
            "gathered_cell_layers",
            "cell_logits",
        ),
    ),
    "data_tools.bundle_files.seals": (
        "data_tools.datasets.index (the one reader of dataset.json, beside the dataset code)",
        ("read_dataset_json", "_read_dataset_json", "_UNSEALED_WARNED"),
    ),
    # loading out of the core: the core reads no file (histojax.loading reads bundles; the format keeps its own names)
    "histojax.core.slide": (
        "histojax.loading (check_levels: data_tools.bundle_files.reading; select_levels, *_bytes: .format)",
        (
            "load_slide",
            "stack_slides",
            "check_alike",
            "check_levels",
            "slide_arrays_from_bundle",
            "tiled_slide_arrays",
            "with_features",
            "slide_label_from_metadata",
            "release_heap",
            "DEFAULT_MAX_DEVICE_BYTES",
            "HOST_PEAK_FACTOR",
            "select_levels",
            "slide_device_bytes",
            "feature_bytes",
            "tumour_table_bytes",
        ),
    ),
    "data_tools.slide_files.tiff": (
        "data_tools.slide_files.base (the TIFF reader is data_tools.slide_files.tiff.TiffSlideReader)",
        ("LevelInfo", "describe", "check_levels", "_check_levels", "SlideReader", "MAX_DECODE_BYTES"),
    ),
}


@pytest.mark.parametrize("old, new", sorted(GONE.items()))
def test_old_path_is_gone(old, new):
    assert importlib.util.find_spec(old) is None, f"{old} still importable; the one path is {new}"
    assert importlib.util.find_spec(new) is not None


@pytest.mark.parametrize("old", sorted(MOVED_NAMES))
def test_moved_names_are_defined_in_their_one_module_only(old):
    """A moved name is not defined in its old module (the facade re-exports nothing; a module that only imports a
    name for its own use still has it as an attribute, so only definitions count)."""
    home, names = MOVED_NAMES[old]
    package = (ROOT / old.replace(".", "/")).is_dir()
    path = ROOT / (old.replace(".", "/") + ("/__init__.py" if package else ".py"))
    tree = ast.parse(path.read_text())
    defined = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    defined |= {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
    if package:  # a package (baselines.common, baselines.evaluate): no re-export at all
        defined |= {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names}
    assert not defined & set(names), f"{old} still defines {sorted(defined & set(names))}; their home is {home}"


def test_nothing_imports_a_moved_name_from_its_old_module():
    """``from OLD import NAME`` and ``OLD.NAME`` (or the last part of OLD, ``head_fit.read_spec``) name nothing moved
    (the dated run records of ``docs/results/`` aside: they name the code as it was on their date)."""
    hits = []
    for old, (_, names) in MOVED_NAMES.items():
        alt = "|".join(re.escape(n) for n in names)
        short = re.escape(old.rsplit(".", 1)[-1])
        pattern = re.compile(
            rf"from {re.escape(old)} import [^\n#]*\b({alt})\b|(?<![\w.]){short}\.({alt})\b"
            rf"|\b{re.escape(old)}\.({alt})\b"
        )
        for path in _text_files():
            if "results" in path.relative_to(ROOT).parts[:2]:
                continue
            for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                if pattern.search(line):
                    hits.append(f"{path.relative_to(ROOT)}:{lineno}: {line.strip()[:100]}")
    assert not hits, "moved names still reached through their old module:\n" + "\n".join(hits)


def _text_files() -> list[pathlib.Path]:
    """Code, tests, docs, examples and the Makefile (this file aside)."""
    files = [
        p
        for d in ("histojax", "data_tools", "baselines", "benchmarks", "experiments", "examples", "tests", "docs")
        if (ROOT / d).is_dir()
        for p in (ROOT / d).rglob("*")
        if p.suffix in (".py", ".md", ".ipynb", ".toml", ".cfg", ".txt") and p.name != "test_import_paths.py"
    ]
    return files + [ROOT / n for n in ("README.md", "Makefile", "pyproject.toml") if (ROOT / n).is_file()]


def test_nothing_names_an_old_path():
    """Code, tests, docs, examples and the Makefile use only the one path of each name."""
    pattern = re.compile(r"\b(" + "|".join(re.escape(o) for o in GONE) + r")\b")
    files = [
        p
        for d in ("histojax", "data_tools", "baselines", "benchmarks", "experiments", "examples", "tests", "docs")
        if (ROOT / d).is_dir()
        for p in (ROOT / d).rglob("*")
        if p.suffix in (".py", ".md", ".ipynb", ".toml", ".cfg", ".txt") and p.name != "test_import_paths.py"
    ]
    files += [ROOT / n for n in ("README.md", "Makefile", "pyproject.toml") if (ROOT / n).is_file()]
    hits = []
    for path in files:
        for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for m in pattern.finditer(line):
                hits.append(f"{path.relative_to(ROOT)}:{lineno}: {m.group(1)}")
    assert not hits, "old import paths still named:\n" + "\n".join(hits)
