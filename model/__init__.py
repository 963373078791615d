"""The denoising network of Kim & Lee (2018) and its CPU training code.

Modules, one job each: ``config`` (ModelConfig, presets), ``transfer`` (radiance <-> network space),
``network`` (densenet / plain CNN), ``loss``, ``patches`` (crops, flat-patch filter, augmentation),
``dataset`` (dataset folder -> images in RAM), ``step`` (one guarded optimiser step, LR schedule),
``checkpoint`` (self-describing safetensors files), ``infer`` (whole-image tiled inference),
``inference_net`` (BN-folded, concatenation-free copy of a network for fast inference),
``validate`` (PSNR/relMSE vs noisy vs OIDN), ``run_log`` (log.jsonl, curves.png),
``train_config`` (TrainConfig), ``train`` (the loop), ``synthetic`` (tiny test datasets),
``errors`` and ``cli`` (the ``train`` command).
"""
