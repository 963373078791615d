"""The denoise engine: everything between a noisy render and its denoised image.

``denoiser`` (:class:`~denoise.denoiser.Denoiser`: models by registry name or file, loaded once) ->
``chain`` (exposure, sanitise, transfer, the network tile by tile, bound, inverse) on ``tiling``'s
exact tiles with the ``folded`` networks (``inference_net``, ``inference_unet``) in the float
format of ``precision``, averaged over the mirrored copies of ``flips`` -> ``ensemble`` (several
networks' outputs weighted per pixel by their estimated error) -> ``noise_guard`` (the render kept
where its noise does not explain the change) -> ``energy`` (local means matched to the render's);
``box_filter`` gives them exact window sums, ``allocator`` keeps the process's memory bounded,
``oidn`` runs Intel Open Image Denoise beside it. Uses :mod:`model` (networks, checkpoints,
registry) and :mod:`imaging`.
"""
from denoise.denoiser import DenoiseResult, Denoiser

__all__ = ["DenoiseResult", "Denoiser"]
