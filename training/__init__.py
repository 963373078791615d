"""Training the networks of :mod:`model`: the ``train`` command (``cli``), its typed config
(``train_config``), recipes that make a shipped model from nothing (``recipe``: the TOML files of
``recipes/``; ``recipe_run``: rendering their data, their stages in order, fine-tunes), datasets in
RAM (``dataset``, ``synthetic``), crops and augmentation (``patches``), batches prepared ahead on the
run's device (``batches``), losses (``loss``), one guarded optimiser step and the LR schedule
(``step``), the loop (``train``), validation through the same chain users run (``validate``,
:mod:`denoise.chain`), DDP (``distributed``), the run's log and curves (``run_log``) and what a
checkpoint's card records (``provenance``). Sits above :mod:`denoise` because validation denoises
exactly as inference does, and above :mod:`dataset_gen` because a recipe renders its data.
"""
