"""The bundle format on disk: what a bundle folder holds and how it is written and read back.

One module per job: :mod:`.format` (the metadata schema and level selection), :mod:`.writes` (atomic writes and the
marked temporaries they leave when interrupted), :mod:`.seals` (the sha256 seal of a bundle and of a dataset's
``dataset.json``), :mod:`.safe_files` (opening only regular files: never a link, FIFO or device) and :mod:`.reading`
(the checked read of a bundle's arrays). Nothing is re-exported here: import the module that defines a name.
"""
