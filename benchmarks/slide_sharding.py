"""Device memory of a dataset with its slides sharded over devices (``--shard-slides``) against
replicated (``--devices N`` alone): bytes of the slide arrays held by each device (from their
addressable shards) and the per-device argument bytes of the compiled PPO program
(``memory_analysis``), on ``N`` fake CPU devices unless real ones exist.

    python benchmarks/slide_sharding.py --devices 4

Without ``--dataset`` a dataset of 8 semi-synthetic slides (``--size`` px, tile 32, Easy levels)
is built in a temporary folder.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", type=int, default=4)
    p.add_argument("--dataset", default=None, help="a dataset folder (dataset.json, split 'all')")
    p.add_argument("--slides", type=int, default=8, help="slides of the built dataset")
    p.add_argument("--size", type=int, default=1024, help="side of the built slides, px")
    args = p.parse_args(argv)
    if "jax" not in sys.modules and "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}"
        ).strip()
    import jax
    import numpy as np
    from jax.sharding import Mesh

    import histojax
    from baselines import ppo
    from baselines.harness.runner import compile_seeds
    from histojax import sharding
    from histojax.datasets import dataset_slides

    if args.dataset:
        paths = [str(s) for s in dataset_slides(args.dataset, "all")]
    else:
        from data_tools.datasets.synth.dataset import make_dataset

        root = Path(tempfile.mkdtemp(prefix="histojax-slide-sharding-"))
        ds = make_dataset(
            root,
            n_slides=args.slides,
            size=(args.size, args.size),
            seed=0,
            tile_size=32,
            level_sets=(3,),
            progress=False,
            previews=False,
        )
        paths = [str(root / s["bundle"]) for s in ds["slides"]]
    n = args.devices
    devices = jax.devices()
    print(f"{len(paths)} slides over {n} of {len(devices)} {devices[0].platform} device(s) ({devices[0].device_kind})")
    _, whole = histojax.make("HistoJAX-Easy-v0", slides=paths)
    whole_bytes = sum(int(a.nbytes) for a in jax.tree.leaves(whole.slide))
    del whole
    mesh = Mesh(np.array(devices[:n]), ("batch",))
    _, params = sharding.make_sharded("HistoJAX-Easy-v0", mesh, slides=paths)
    per = sharding.device_bytes(params.slide)
    print(f"the dataset on one device: {whole_bytes:,} bytes")
    print(
        "sharded, per device: "
        + ", ".join(f"{per[d]:,}" for d in mesh.devices.flat)
        + f" bytes ({max(per.values()) / whole_bytes:.1%} of the dataset each; 1/{n} = {1 / n:.1%})"
    )
    del params
    config = dict(
        env_id="HistoJAX-Easy-v0",
        num_envs=8 * n,
        num_steps=16,
        total_timesteps=16 * 8 * n,
        update_epochs=1,
        num_minibatches=2,
        hidden=32,
        num_seeds=1,
        print_progress=False,
        devices=n,
        env_kwargs={"slides": paths},
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    for shard in (False, True):
        train = ppo.make_train({**config, "shard_slides": shard})
        stats = compile_seeds(train, keys).exe.memory_analysis()
        print(
            f"PPO --devices {n}{' --shard-slides' if shard else ''}: compiled program's arguments per device "
            f"{stats.argument_size_in_bytes:,} bytes, temporaries {stats.temp_size_in_bytes:,}"
        )
        del train
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
