"""Host memory of the two steps issue 18 measured, each in a child process so its peak RSS is its own:

* ``make`` on a dense bundle: peak RSS (VmHWM) rise over the imports against the bytes put on the device
  (on the CPU backend the device copy lives in host RAM too, so it is part of the rise);
* a tiled build of a single-level (non-pyramidal) TIFF: peak RSS of the build (``--single`` writes one
  from a semi-synthetic pyramid first; sizes in px a side). Linux only (``/proc/self/status``).

    python benchmarks/host_memory.py [--size 8192] [--single 20000] [--out /tmp/histojax-host-memory]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

_MAKE = """
import sys, warnings
warnings.simplefilter("ignore")
import jax, histojax
def status(key):  # kB → bytes
    return int(next(l for l in open("/proc/self/status") if l.startswith(key)).split()[1]) * 1024
with open("/proc/self/clear_refs", "w") as f:  # reset the peak (VmHWM), which a child inherits at fork
    f.write("5")
base = status("VmRSS:")
env, params = histojax.make("HistoJAX-Hard-v0", slide=sys.argv[1])
device = sum(int(a.nbytes) for a in jax.tree.leaves(params.slide))
rise = status("VmHWM:") - base
print(f"make (Hard, 7 levels): {device / 2**20:.0f} MiB on the device, peak RSS rise {rise / 2**20:.0f} MiB "
      f"({rise / device:.2f}x the device bytes; backend {jax.default_backend()})")
"""

_BUILD = """
import sys, time, warnings
warnings.simplefilter("ignore")
from data_tools.bundle import build_bundle
with open("/proc/self/clear_refs", "w") as f:  # reset the peak (VmHWM), which a child inherits at fork
    f.write("5")
t0 = time.perf_counter()
build_bundle(sys.argv[1], sys.argv[2], storage="tiled", progress=False, overwrite=True)
hwm = int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM:")).split()[1]) * 1024
print(f"tiled build of {sys.argv[1]}: peak RSS {hwm / 2**20:.0f} MiB, {time.perf_counter() - t0:.0f} s")
"""


def single_level_tiff(pyramid: Path, out: Path, tile: int = 512) -> Path:
    """Level 0 of ``pyramid`` rewritten as a single-level tiled JPEG TIFF, one tile at a time."""
    import numpy as np
    import tifffile

    from data_tools.slides import open_slide

    with open_slide(pyramid) as r:
        w, h = r.dimensions
        tiles = (r.read_region(0, x, y, tile, tile) for y in range(0, h, tile) for x in range(0, w, tile))
        tifffile.imwrite(out, tiles, shape=(h, w, 3), dtype=np.uint8, tile=(tile, tile), photometric="rgb",
                         compression="jpeg")
    return out


def main(argv=None) -> int:
    """Print the figures; returns 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=8192, help="side in px of the dense bundle's slide (default 8192)")
    p.add_argument("--single", type=int, default=0, help="side in px of a single-level TIFF to build tiled (0: skip)")
    p.add_argument("--out", default="/tmp/histojax-host-memory")
    args = p.parse_args(argv)
    from data_tools.bundle import build_bundle
    from data_tools.datasets.synth_large import make_large_slide

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    slide = out / f"pyramid{args.size}.tif"
    if not slide.exists():
        make_large_slide(slide, size=args.size, tissue_fraction=0.1, seed=0, progress=False)
    bundle = out / f"dense{args.size}"
    if not bundle.exists():
        build_bundle(slide, bundle, annotations_path=slide.with_suffix(".geojson"), tile_size=64,
                     magnification_range=16, progress=False)
    subprocess.run([sys.executable, "-c", _MAKE, str(bundle)], check=True)
    if args.single:
        pyramid = out / f"pyramid{args.single}.tif"
        if not pyramid.exists():
            make_large_slide(pyramid, size=args.single, tissue_fraction=0.1, seed=0, progress=False)
        single = out / f"single{args.single}.tif"
        if not single.exists():
            single_level_tiff(pyramid, single)
        subprocess.run([sys.executable, "-c", _BUILD, str(single), str(out / f"tiled{args.single}")], check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
