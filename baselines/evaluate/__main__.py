"""``python -m baselines.evaluate``: the same command as ``histojax evaluate``."""

from baselines.evaluate.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
