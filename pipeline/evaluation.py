"""The one evaluation path: render in two halves -> denoise as ``render-and-denoise`` does -> score.

``render-and-denoise`` (:mod:`pipeline.run`, budget mode included), ``tradeoff``
(:mod:`pipeline.tradeoff`) and the benchmarks that render and score (``benchmarks/evaluate.py``,
``benchmarks/noise_guard.py``, ``benchmarks/budget.py``) all go through these functions, so a
scoreboard measures exactly what users get:

* :func:`render_input`: the render a denoiser is given. With the noise guard on (the default) it is
  made of two halves of independent samples; their difference is the variance estimate that feeds
  a model's noise input and the guard. Off: one piece, no variance.
* :func:`denoise_output`: one model through :meth:`Denoiser.denoise_render` (its AOVs, noise input
  and the guard at the strength for the render's spp), or OIDN on the same render, colour-only and
  with the render's albedo and normals (:func:`oidn_output`); with ``keep_network`` the bare
  network's output (the same forward pass, before the guard) too.
* :func:`with_aovs`: the albedo and normals OIDN + albedo + normal takes, for a render made
  without them (our shipped models take none). They come from a pass of Mitsuba's aov integrator
  alone on the same loaded scene, with the render's spp, seed and halves: the same camera rays.
  The render our models see is the one they saw without it, bit for bit; wrapping the scene's
  integrator in the aov integrator instead changes a volpath scene's radiance by float rounding,
  and costs more render time (``benchmarks/aov_cost.py``).
* :func:`score`: PSNR (tonemapped), relMSE and FLIP against the reference (:mod:`imaging.metrics`).

:func:`evaluate` chains the three for one scene, spp and seed.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from imaging.errors import DenoiserError
from imaging.exr import read_exr
from imaging.output_paths import check_not_inputs
from imaging.metrics import all_metrics, flip, psnr, relmse
from rendering.render import (DEFAULT_MAX_MEMORY_MB, Progress, RenderResult, check_render_memory, load_scene,
                              pass_seeds, prepare, render_aovs, render_loaded)
from rendering.render_crops import film_window
from denoise.denoiser import DenoiseResult, Denoiser
from denoise.energy import settings_if
from denoise.oidn import oidn_denoise

AOVS = ("albedo", "sh_normal")  # what a model with auxiliary inputs, and OIDN's, need rendered
OIDN = "oidn"  # OIDN colour-only
OIDN_AUX = "oidn_aux"  # OIDN + albedo + normal
OIDN_LABELS = {OIDN: "OIDN colour-only", OIDN_AUX: "OIDN + albedo + normal"}
BARE = " bare"  # suffix of a model's bare network output in :func:`denoise_outputs`


@dataclass
class RenderSettings:
    """How a command renders its scene and what it compares with (filled by the CLI, saved in
    config.json). ``resolution`` [W, H] (None: the scene's own); ``params``: the scene's
    ``$parameters``; ``max_memory_mb`` bounds the render's films and the denoiser's tiles;
    ``noise_guard``: render in two halves and guard the models (off: one piece, the network's
    output as it is); ``skip_below``: with the halves, leave the parts whose noise is below this out
    of the network (:class:`denoise.denoiser.Denoiser`; None: run it everywhere); ``precision``: the
    denoisers' float format (:mod:`denoise.precision`); ``flips``: test-time flips of the networks
    (:mod:`denoise.flips`); ``energy``: match the output's local means to the render's
    (:mod:`denoise.energy`); ``device``: where the networks run (:func:`model.device.choose_device`);
    the reference is an EXR file or a render at ``reference_spp`` (another seed). ``overwrite``:
    outputs may replace the scene or reference file (:mod:`imaging.output_paths`)."""

    scene: str
    resolution: tuple[int, int] | None = None
    seed: int = 0
    params: dict[str, str] = field(default_factory=dict)
    max_memory_mb: float = DEFAULT_MAX_MEMORY_MB
    noise_guard: bool = True
    skip_below: float | None = None
    precision: str = "auto"
    flips: int = 1
    energy: bool = True
    device: str = "cpu"
    reference: str | None = None
    reference_spp: int | None = None
    overwrite: bool = False

    def check_outputs(self, out: str | Path, names: Iterable[str]) -> None:
        """Raise :class:`imaging.output_paths.OutputPathError` when a file the command writes into
        ``out`` (``names``) is its scene or reference file, or a link to one (unless ``overwrite``)."""
        check_not_inputs([Path(out) / name for name in names], [self.scene, self.reference], self.overwrite)

    def check(self, reference_required: bool = False) -> None:
        """Raise :class:`DenoiserError` for both references given (or none, when one is required)."""
        if self.reference and self.reference_spp:
            raise DenoiserError("give either --reference or --reference-spp, not both")
        if reference_required and not (self.reference or self.reference_spp):
            raise DenoiserError("give one of --reference FILE or --reference-spp N (errors are measured "
                                "against it)")

    def load(self, aovs: Sequence[str] = ()) -> Any:
        """The scene prepared (box filter, float32 film, ``aovs``) and loaded: a ``mi.Scene``."""
        return load_scene(prepare(self.scene, self.resolution, aovs, self.params))


def make_denoiser(model: str | Path | Sequence[str | Path] | None, settings: RenderSettings) -> Denoiser:
    """The denoiser of ``model`` with the settings' memory bound, precision, flips, energy
    correction and, with the halves, skipping."""
    return Denoiser(model, max_memory_mb=settings.max_memory_mb, precision=settings.precision,
                    flips=settings.flips, energy=settings_if(settings.energy),
                    skip_below=settings.skip_below if settings.noise_guard else None, device=settings.device)


def aovs_for(denoisers: Iterable[Any]) -> tuple[str, ...]:
    """The AOVs to render for these models (loaded, or a time budget's recorded costs: each with
    ``needs_aovs``): :data:`AOVS` if any of them needs them, else none."""
    return AOVS if any(d.needs_aovs for d in denoisers) else ()


def check_memory(scene: Any, settings: RenderSettings, spp: int, aovs: Sequence[str] = (),
                 held: Sequence[str] = ()) -> None:
    """Refuse, before anything is rendered, a loaded scene whose film is too large for the memory
    left: :func:`rendering.render.check_render_memory` for :func:`render_input`'s render at
    ``spp`` with ``held``, the other images of the film's size the command keeps beside it."""
    _, _, width, height = film_window(scene)
    check_render_memory(width, height, aovs, settings.noise_guard and spp >= 2, settings.max_memory_mb, held,
                        settings.scene)


def render_input(scene: Any, spp: int, settings: RenderSettings, aovs: Sequence[str] = (),
                 progress: Progress | None = None) -> RenderResult:
    """The render a denoiser is given: ``spp`` samples at ``settings.seed``, in two halves (with
    their variance) unless the noise guard is off; ``progress`` as :func:`render_loaded`'s."""
    return render_loaded(scene, spp, settings.seed, aovs, halves=settings.noise_guard,
                         max_memory_mb=settings.max_memory_mb, progress=progress)


def with_aovs(render: RenderResult, scene: Any, settings: RenderSettings) -> tuple[RenderResult, float]:
    """``render`` (the same ``rgb`` array) with :data:`AOVS`, and the seconds their pass took (0:
    the render had them). The pass renders ``scene`` (the one loaded scene that made ``render``)
    at the render's spp, the settings' seed and halves with Mitsuba's aov integrator alone
    (:func:`rendering.render.render_aovs`): the camera rays of the render, no light transport."""
    if all(name in render.aovs for name in AOVS):
        return render, 0.0
    aovs = render_aovs(scene, render.spp, settings.seed, AOVS, halves=settings.noise_guard,
                       max_memory_mb=settings.max_memory_mb)
    return replace(render, aovs={**render.aovs, **aovs.aovs}), aovs.seconds


def read_reference(settings: RenderSettings) -> np.ndarray | None:
    """The reference EXR's HxWx3 radiance (read before rendering, so a bad file fails early), or
    None when there is none or it is to be rendered (:func:`render_reference`)."""
    return read_exr(settings.reference, max_bytes=settings.max_memory_mb * 2**20).rgb if settings.reference else None


def render_reference(settings: RenderSettings, scene: Any, aovs: Sequence[str] = (),
                     progress: Progress | None = None) -> RenderResult:
    """The reference at ``settings.reference_spp`` with a seed of its own; ``scene`` is reused
    unless it renders AOVs (then the scene is loaded again without them)."""
    plain = settings.load() if aovs else scene
    return render_loaded(plain, settings.reference_spp, pass_seeds(settings.seed, 2)[1],
                         max_memory_mb=settings.max_memory_mb, progress=progress)


def check_reference(settings: RenderSettings, reference: np.ndarray, render: RenderResult) -> None:
    """Raise :class:`DenoiserError` when the reference and the render differ in size."""
    if reference.shape != render.rgb.shape:
        raise DenoiserError(f"{settings.reference}: reference is {reference.shape[1]}x{reference.shape[0]}, "
                            f"render is {render.rgb.shape[1]}x{render.rgb.shape[0]}")


@dataclass
class Output:
    """A denoiser's image of a render (HxWx3 float32 linear radiance) and its seconds; ``result``
    is our model's whole :class:`DenoiseResult` (None for OIDN)."""

    image: np.ndarray
    seconds: float
    result: DenoiseResult | None = None


def oidn_output(render: RenderResult, aux: bool = False) -> Output:
    """OIDN on ``render`` (the anchor, as it comes: no guard): colour-only, or with ``aux`` its
    albedo and normals as OIDN's auxiliary images (:func:`with_aovs`)."""
    if not aux:
        return Output(*oidn_denoise(render.rgb))
    return Output(*oidn_denoise(render.rgb, render.aovs["albedo"], render.aovs["sh_normal"]))


def denoise_output(render: RenderResult, denoiser: Denoiser | None, keep_network: bool = False) -> Output:
    """``denoiser`` applied to ``render`` as ``render-and-denoise`` applies it; None: OIDN
    colour-only (:func:`oidn_output`). ``keep_network``: keep the bare network's output in
    ``result.network``."""
    if denoiser is None:
        return oidn_output(render)
    result = denoiser.denoise_render(render, keep_network)
    return Output(result.image, result.seconds, result)


def denoise_outputs(render: RenderResult, denoisers: Mapping[str, Denoiser], oidn: bool = False,
                    bare: bool = False) -> dict[str, Output]:
    """Every model's :func:`denoise_output` under its name; with ``bare`` also its bare network
    output (``NAME bare``, the same forward pass: the seconds are the model's); with ``oidn``,
    OIDN colour-only under :data:`OIDN` and, when the render has :data:`AOVS`, OIDN + albedo +
    normal under :data:`OIDN_AUX`."""
    outputs: dict[str, Output] = {}
    for name, denoiser in denoisers.items():
        output = outputs[name] = denoise_output(render, denoiser, keep_network=bare)
        if bare:
            assert output.result is not None and output.result.network is not None
            outputs[name + BARE] = Output(output.result.network, output.seconds)
    if oidn:
        outputs[OIDN] = oidn_output(render)
        if all(name in render.aovs for name in AOVS):
            outputs[OIDN_AUX] = oidn_output(render, aux=True)
    return outputs


def score(image: np.ndarray, reference: np.ndarray, full: bool = False) -> dict[str, float]:
    """PSNR dB (tonemapped), relMSE and FLIP of ``image`` against ``reference``; ``full``: every
    metric of :func:`imaging.metrics.all_metrics` (SSIM, SMAPE, HDR-FLIP too)."""
    if full:
        return all_metrics(image, reference)
    return {"psnr": psnr(image, reference), "relmse": relmse(image, reference), "flip": flip(image, reference)}


@dataclass
class Evaluation:
    """One scene at one spp: the render (with OIDN, its AOVs too), each denoiser's output and the
    scores of ``noisy`` (the render) and of every output; ``aov_seconds``: the AOV pass's time
    (:func:`with_aovs`; None without OIDN)."""

    render: RenderResult
    outputs: dict[str, Output]
    scores: dict[str, dict[str, float]]
    aov_seconds: float | None = None


def evaluate(scene: Any, spp: int, settings: RenderSettings, reference: np.ndarray,
             denoisers: Mapping[str, Denoiser], oidn: bool = True, bare: bool = False,
             aovs: Sequence[str] = ()) -> Evaluation:
    """Render ``scene`` at ``spp`` as :func:`render_input` does, denoise it with every model (and,
    with ``oidn``, OIDN colour-only and, its AOVs added by :func:`with_aovs`, OIDN + albedo +
    normal) as :func:`denoise_outputs` does, and score everything against ``reference``."""
    render = render_input(scene, spp, settings, aovs)
    check_reference(settings, reference, render)
    aov_seconds = None
    if oidn:
        render, aov_seconds = with_aovs(render, scene, settings)
    outputs = denoise_outputs(render, denoisers, oidn, bare)
    scores = {"noisy": score(render.rgb, reference)}
    scores.update({name: score(output.image, reference) for name, output in outputs.items()})
    return Evaluation(render, outputs, scores, aov_seconds)


def quality_lines(quality: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The console table of :func:`score`'s full figures per image (``noisy``, ``denoised``...)."""
    lines = [f"{'':10}{'PSNR dB':>9}{'SSIM':>8}{'relMSE':>10}{'FLIP':>8}"]
    for name, m in quality.items():
        psnr = "inf" if m["psnr"] is None else f"{m['psnr']:.2f}"
        lines.append(f"{name:10}{psnr:>9}{m['ssim']:>8.4f}{m['relmse']:>10.5f}{m['flip']:>8.4f}")
    return lines
