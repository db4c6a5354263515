"""Image morphs as time-discrete geodesics in the metamorphosis model, NumPy in and out.

A morph from ``a`` to ``b`` is a path of ``K + 1`` frames ``u_0 = a, ..., u_K = b``; each step
is a small smooth deformation plus a small change of intensity, found by minimising the path
energy of Effland, Kobler, Pock, Rajkovic and Rumpf, "Image Morphing in Deep Feature
Spaces" (the repository's SPEC.md is the exact contract). Two models: ``"rgb"`` compares
colours, ``"deep"`` compares VGG19 features (weights from a file you give).

>>> import deepmorph, numpy as np
>>> m = deepmorph.morph("a.png", "b.png", K=8)              # doctest: +SKIP
>>> m.frames.shape, m.deformations.shape                     # doctest: +SKIP
((9, 256, 256, 3), (8, 2, 256, 256))
>>> m.save("out")                                            # doctest: +SKIP

Every setting left at ``None`` takes the library's default (``deepmorph.defaults()`` shows
them all); the native module is the same Rust code as the ``deepmorph`` program, so a morph
made here equals the program's on the same inputs and settings.
"""

from __future__ import annotations

import sys
import warnings
from typing import Any, Callable, Optional, Union

from . import _native
from ._native import Interrupted, Morph, __version__, backends, defaults, evaluate, warp

__all__ = [
    "Interrupted",
    "Morph",
    "__version__",
    "backends",
    "defaults",
    "evaluate",
    "inbetween",
    "morph",
    "warp",
]


def morph(
    a: Any,
    b: Any,
    *,
    K: Optional[int] = None,
    model: str = "rgb",
    vgg19: Optional[Union[str, "os.PathLike[str]"]] = None,
    size: Optional[Union[int, "tuple[int, int]"]] = None,
    levels: Optional[int] = None,
    sweeps: Optional[int] = None,
    tol: Optional[float] = None,
    quality: Optional[str] = None,
    schedule: Optional[str] = None,
    backend: Optional[str] = None,
    points: Any = None,
    align: Optional[str] = None,
    progress: Union[bool, Callable[[dict], None]] = False,
    **params: Any,
) -> Morph:
    """Morph ``a`` into ``b``; returns a :class:`Morph`.

    ``a``, ``b``: image paths (any format the program reads) or arrays ``[H, W, 3]`` of
    ``uint8`` (0..255) or float (0..1). Both paths: the run records them, as the program
    does; arrays are recorded by their sizes. B is resized to A's working size.

    ``K``: steps (``K + 1`` frames). ``model``: ``"rgb"`` or ``"deep"`` (needs ``vgg19``, an
    ONNX or safetensors VGG19). ``size``: the longest side of the working size (aspect kept,
    never enlarged) or an exact ``(height, width)``. ``levels``, ``sweeps``: the multilevel
    pyramid and iPALM sweeps per level. ``tol``: stop a level once ``E`` falls by less than
    this (relative) over 10 sweeps; 0 runs every sweep. ``quality``: ``"draft"``,
    ``"standard"`` or ``"paper"`` (sets size, levels, sweeps, tolerance; arguments given
    beside it win). ``schedule``: ``"sequential"`` or ``"batched"``. ``backend``: ``"flex"``,
    ``"ndarray"`` or ``"wgpu"``. ``points``: landmark pairs ``(x_a, y_a, x_b, y_b)`` in each
    image's own pixels, as a points file (CSV/JSON), a list or an ``[N, 4]`` array.
    ``align``: ``"similarity"`` or ``"affine"`` starts from a global map (from the points,
    else from the images).

    ``progress``: ``True`` draws a progress bar (tqdm when installed, else one line per
    level on stderr); a callable receives a dict after every sweep (``level``, ``levels``,
    ``size``, ``phase``, ``sweep``, ``sweeps``, ``energy``, ``data``, ``regularizer``,
    ``landmarks``, ``seconds``, ``stop``); an exception it raises stops the morph after that
    sweep and propagates.

    ``**params``: any other setting by its ``config.json`` name: ``delta``, ``lambda_``,
    ``mu``, ``xi1``, ``xi2``, ``sigma``, ``rho``, ``beta``, ``safeguard``,
    ``landmark_weight``, ``eta``, ``feature_rms``, ``pre_sweeps``, ``max_memory``, ``video``,
    ``fps``, ``crf``, ``frames``, ``pingpong``, ``init``...; an unknown name is a
    ``ValueError`` listing them.

    A NaN or infinity in the optimisation ends the morph early with the last finite path
    and a ``RuntimeWarning`` (``.termination`` says where). The solve releases the GIL.
    Ctrl-C stops it after the current step and raises :class:`Interrupted` (a
    ``KeyboardInterrupt``) whose ``.morph`` holds the path reached.
    Bad settings and inputs raise ``ValueError``, missing files ``FileNotFoundError``, a
    morph too large for the memory ``MemoryError``, with the program's messages.
    """
    callback, finish = _progress(progress)
    try:
        result = _native.morph(
            a,
            b,
            K=K,
            model=model,
            vgg19=vgg19,
            size=size,
            levels=levels,
            sweeps=sweeps,
            tol=tol,
            quality=quality,
            schedule=schedule,
            backend=backend,
            points=points,
            align=align,
            progress=callback,
            **params,
        )
    finally:
        finish()
    if result.termination != "completed":
        # A NaN or infinity stopped the solver: the result is the last finite path.
        warnings.warn(f"deepmorph: {result.termination}", RuntimeWarning, stacklevel=2)
    return result


def inbetween(morph: Morph, n: int) -> "numpy.ndarray":
    """``n`` frames evenly spaced in time along ``morph``'s path, float32 ``[n, H, W, 3]``:
    its ``K + 1`` frames among them, the frames between following the deformations (the
    program's ``--frames n``)."""
    return morph.inbetween(n)


def _progress(progress: Union[bool, Callable[[dict], None], None]):
    """The callback for ``progress`` and what closes it."""
    if callable(progress):
        return progress, lambda: None
    if not progress:
        return None, lambda: None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return _lines(), lambda: None
    bar = None

    def update(event: dict) -> None:
        nonlocal bar
        if event["phase"] != "joint":
            return
        total = event["levels"] * event["sweeps"]
        if bar is None:
            bar = tqdm(total=total, unit="sweep", file=sys.stderr)
        done = event["level"] * event["sweeps"] + event["sweep"]
        h, w = event["size"]
        bar.set_description(f"level {event['level'] + 1}/{event['levels']} {w}x{h}", refresh=False)
        bar.set_postfix(E=f"{event['energy']:.5g}", refresh=False)
        bar.update(done - bar.n)

    def finish() -> None:
        if bar is not None:
            bar.close()

    return update, finish


def _lines() -> Callable[[dict], None]:
    """Progress without tqdm: one line per level as it ends."""

    def update(event: dict) -> None:
        if event["phase"] == "joint" and event["stop"] is not None:
            h, w = event["size"]
            print(
                f"deepmorph: level {event['level'] + 1}/{event['levels']} ({w}x{h}) "
                f"{event['sweep']} sweeps, E = {event['energy']:.6g}, "
                f"{event['seconds']:.1f} s ({event['stop']})",
                file=sys.stderr,
            )

    return update
