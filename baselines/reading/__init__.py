"""The reading baselines: fitting slide heads, scripted and trained readers scored through a head, the budget
curve, and the navigator's diagnosis through a head. Each is a command, ``python -m baselines.reading.<name>``:

- ``head_fit``: fit the calibrated pooled-logit head (:mod:`histojax.reading.heads.logit`).
- ``head_mil_fit``: fit the trained heads (:mod:`histojax.reading.heads.mil`) and choose one on validation.
- ``learned_head_fit``: fit the learned attention-MIL head on any features (:mod:`histojax.reading.heads.learned`).

(The fits keep the command names published records and run commands name, e.g. the published learned head's
``config.json``; the head each fits: ``head_fit`` → ``logit``, ``head_mil_fit`` → ``mil``, ``learned_head_fit`` →
``learned``.)
- ``readers``: scripted readers, CAMELYON lesion classes and the budget curve with one head for every row.
- ``budget_curve``: AUC and accuracy against the fraction read (``histojax budget-curve``).
- ``diagnosis``: navigators scored through a head beside the readers.
- ``train_readers``: readers and navigators trained with the head reward, then scored.

The commands stand on libraries (no command imports another command's module for a loader):

- ``fitting``: the rules the logit and MIL head fits share (fewest slides per class, the chosen head's refusal, the
  1-D logistic calibration).
- ``slides``: the slide loaders every head-based tool shares (``read_spec``, ``load_slide(s)``, ``read_bundle``,
  ``finest_views``, ``scale_warning``, ``HeadDataError``) and the CAMELYON lesion classes of a loaded slide.
- ``pipeline``: the readers and the budget curve as one pipeline (the default reading ``BUDGETS``, the one loader of
  a split's slides, the one run loop over readers × budgets, the one-class refusal, trained readers' roll-outs).
- ``reader_scores``: read masks scored through one head (cells and read masks, the head's scores, the scripted readers'
  results, their rows and tables, the split with its head): what ``readers``, ``diagnosis`` and ``budget_curve`` share.
- ``orders`` (the scripted readers' cell orders and the glimpse env's reading rule), ``plots`` (the figures),
  ``csv_files`` (the tables) and ``provenance`` (what a head was fitted on, and the refusals it implies).
"""
