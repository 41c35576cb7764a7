"""Building datasets: ``data_tools dataset`` (a folder of real slides) and the shared machinery that
``data_tools c16`` also uses — labels and splits (:mod:`.split`), locks, resume and leftovers
(:mod:`.locks`), shards and ``dataset.json`` (:mod:`.build`), slide discovery (:mod:`.discover`)."""

from data_tools.datasets.build import build_dataset, merge_dataset, write_dataset_json
from data_tools.datasets.locks import clean_stale, file_lock
from data_tools.datasets.split import parse_shard, read_label_table, seeded_split, shard_names

__all__ = [
    "build_dataset",
    "clean_stale",
    "file_lock",
    "merge_dataset",
    "parse_shard",
    "read_label_table",
    "seeded_split",
    "shard_names",
    "write_dataset_json",
]
