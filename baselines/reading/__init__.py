"""The reading baselines: fitting slide heads, scripted and trained readers scored through a head, the budget
curve, and the navigator's diagnosis through a head. Each is a command, ``python -m baselines.reading.<name>``:

- ``head_fit``: fit the calibrated pooled-logit head (:mod:`histojax.reading.heads.logit`).
- ``head_mil_fit``: fit the trained heads (:mod:`histojax.reading.heads.mil`) and choose one on validation.
- ``readers``: scripted readers, CAMELYON lesion classes and the budget curve with one head for every row.
- ``budget_curve``: AUC and accuracy against the fraction read (``histojax budget-curve``).
- ``diagnosis``: navigators scored through a head beside the readers.
- ``train_readers``: readers and navigators trained with the head reward, then scored.

The readers and the budget curve are one pipeline, ``pipeline`` (the one loader of a split's slides, the one run loop
over readers × budgets, the one-class refusal, trained readers' roll-outs), with one set of pieces (leaf modules, no
command): ``budgets`` (the default reading budgets), ``orders`` (the scripted readers' cell orders and the glimpse
env's reading rule), ``lesions`` (CAMELYON lesion classes), ``plots`` (their figures) and ``csv_files`` (their tables).
"""
