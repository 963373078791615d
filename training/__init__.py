"""Training the networks of :mod:`model`: the ``train`` command (``cli``), its typed config
(``train_config``), datasets in RAM (``dataset``, ``synthetic``), crops and augmentation (``patches``),
losses (``loss``), one guarded optimiser step and the LR schedule (``step``), the loop (``train``),
validation through the same chain users run (``validate``, :mod:`denoise.chain`), DDP
(``distributed``) and the run's log and curves (``run_log``). Sits above :mod:`denoise` because
validation denoises exactly as inference does.
"""
