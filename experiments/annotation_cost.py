"""Cost of reading hostile annotation files (issue 26, items 9 and 10): time to load (or refuse) an ASAP
XML of many tangled polygons, and peak RSS of loading a large ASAP XML of many small polygons.

    python -m experiments.annotation_cost [--repo PATH] [--tangled 60 --vertices 600] [--big-mb 37]

``--repo`` measures another checkout's ``data_tools`` (e.g. a ``git archive`` of an older commit) with
the same files. Each measurement runs in a fresh subprocess; files are written to a temporary folder.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_MEASURE = """
import resource, sys, time, warnings
sys.path.insert(0, sys.argv[1])
from data_tools.annotations import load_annotations
from data_tools.errors import AnnotationError
warnings.simplefilter("ignore")
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
try:
    ann = load_annotations(sys.argv[2])
    result = f"loaded, {sum(ann.n_polygons.values())} polygons"
except AnnotationError as e:
    result = "refused: " + e.problem[:110]
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(f"{time.perf_counter() - t:.1f} s, peak RSS {peak / 1024:.0f} MiB ({(peak - base) / 1024:.0f} MiB above "
      f"the {base / 1024:.0f} MiB after imports); {result}")
"""


def tangled_xml(path: Path, n_polygons: int, n_vertices: int) -> Path:
    """ASAP XML of ``n_polygons`` polygons of ``n_vertices`` random vertices each (self-intersecting)."""
    with open(path, "w") as f:
        f.write("<ASAP_Annotations><Annotations>")
        for i in range(n_polygons):
            pts = np.random.default_rng(i).integers(0, 10_000, (n_vertices, 2)).tolist()
            f.write(
                f'<Annotation Name="A{i}" Type="Polygon" PartOfGroup="metastasis"><Coordinates>'
                + "".join(f'<Coordinate Order="{j}" X="{x}" Y="{y}" />' for j, (x, y) in enumerate(pts))
                + "</Coordinates></Annotation>"
            )
        f.write("</Annotations></ASAP_Annotations>")
    return path


def big_xml(path: Path, mib: float) -> Path:
    """ASAP XML of disjoint 100-vertex circles (ASAP's own layout), about ``mib`` MiB."""
    n = max(1, int(mib * 2**20 / 6000))  # ~6 kB per annotation
    with open(path, "w") as f:
        f.write('<?xml version="1.0"?>\n<ASAP_Annotations>\n\t<Annotations>\n')
        for i in range(n):
            cx, cy = 300.0 * (i % 300) + 150, 300.0 * (i // 300) + 150
            f.write(
                f'\t\t<Annotation Name="Annotation {i}" Type="Polygon" PartOfGroup="metastasis" '
                'Color="#F4FA58">\n\t\t\t<Coordinates>\n'
            )
            for j in range(100):
                t = 2 * math.pi * j / 100
                f.write(
                    f'\t\t\t\t<Coordinate Order="{j}" X="{cx + 100 * math.cos(t):.4f}" '
                    f'Y="{cy + 100 * math.sin(t):.4f}" />\n'
                )
            f.write("\t\t\t</Coordinates>\n\t\t</Annotation>\n")
        f.write("\t</Annotations>\n\t<AnnotationGroups />\n</ASAP_Annotations>\n")
    return path


def measure(repo: str, path: Path) -> str:
    out = subprocess.run([sys.executable, "-c", _MEASURE, repo, str(path)], capture_output=True, text=True)
    return out.stdout.strip() or out.stderr.strip().splitlines()[-1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repo", default=str(Path(__file__).resolve().parents[1]))
    p.add_argument("--tangled", type=int, default=60, help="tangled polygons in the file")
    p.add_argument("--vertices", type=int, default=600, help="random vertices per tangled polygon")
    p.add_argument("--big-mb", type=float, default=37.0, help="size of the large XML, MiB")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t = tangled_xml(Path(tmp) / "tangled.xml", args.tangled, args.vertices)
        print(
            f"{args.tangled} tangled polygons of {args.vertices} vertices ({t.stat().st_size / 1e3:.0f} KB): "
            f"{measure(args.repo, t)}"
        )
        t.unlink()
        b = big_xml(Path(tmp) / "big.xml", args.big_mb)
        print(f"ASAP XML of {b.stat().st_size / 2**20:.0f} MiB: {measure(args.repo, b)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
