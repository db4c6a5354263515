"""Type stubs of deepmorph (the native module's classes and functions and their Python
wrappers). Settings left at ``None`` take the library's defaults: ``defaults()`` lists them."""

import os
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str

PathLike = Union[str, "os.PathLike[str]"]
ImageLike = Union[PathLike, npt.NDArray[np.uint8], npt.NDArray[np.floating[Any]]]
PointsLike = Union[PathLike, Sequence[Sequence[float]], npt.NDArray[np.floating[Any]]]

class Interrupted(KeyboardInterrupt):
    """Ctrl-C stopped a morph after its current step; ``morph`` holds the path reached."""

    morph: "Morph"

class Morph:
    """A finished (or interrupted) morph."""

    @property
    def frames(self) -> npt.NDArray[np.float32]:
        """``u_0 .. u_K``, ``[K+1, H, W, 3]`` in ``[0, 1]`` (read-only)."""
    @property
    def deformations(self) -> npt.NDArray[np.float32]:
        """``phi_1 .. phi_K``, ``[K, 2, H, W]`` in pixels, ``[:, 0]`` rows: ``phi_k(x)`` is
        where pixel ``x`` of frame ``k - 1`` lies in frame ``k`` (read-only)."""
    @property
    def composed(self) -> npt.NDArray[np.float32]:
        """``Phi = phi_K o ... o phi_1``, ``[2, H, W]``: where each pixel of A lies in B
        (read-only)."""
    @property
    def energy(self) -> dict[str, Any]:
        """``energy.csv`` as columns, one entry per sweep."""
    @property
    def config(self) -> dict[str, Any]:
        """``config.json``."""
    @property
    def metrics(self) -> dict[str, Any]:
        """``metrics.json``'s numbers (computed on first access)."""
    @property
    def termination(self) -> str:
        """``"completed"``, or where the run was interrupted or stopped."""
    @property
    def seconds(self) -> float:
        """Seconds the solver ran."""
    @property
    def notes(self) -> list[str]:
        """What preparing and starting the morph told (resizing, alignment, warnings)."""
    def save(self, dir: PathLike, *, force: bool = False) -> str:
        """Write the morph as ``deepmorph morph -o dir`` does; returns the folder."""
    def inbetween(self, count: int) -> npt.NDArray[np.float32]:
        """``count`` frames evenly spaced along the path, ``[count, H, W, 3]``."""

def morph(
    a: ImageLike,
    b: ImageLike,
    *,
    K: Optional[int] = None,
    model: str = "rgb",
    vgg19: Optional[PathLike] = None,
    size: Optional[Union[int, tuple[int, int]]] = None,
    levels: Optional[int] = None,
    sweeps: Optional[int] = None,
    tol: Optional[float] = None,
    quality: Optional[str] = None,
    schedule: Optional[str] = None,
    backend: Optional[str] = None,
    points: Optional[PointsLike] = None,
    align: Optional[str] = None,
    progress: Union[bool, Callable[[dict[str, Any]], None]] = False,
    **params: Any,
) -> Morph:
    """Morph ``a`` into ``b`` (see ``help(deepmorph.morph)``)."""

def inbetween(morph: Morph, n: int) -> npt.NDArray[np.float32]:
    """``n`` frames evenly spaced along ``morph``'s path, ``[n, H, W, 3]``."""

def evaluate(
    dir: PathLike,
    truth: Optional[PathLike] = None,
    *,
    points: Optional[PathLike] = None,
    vgg19: Optional[PathLike] = None,
    resample_truth: bool = False,
    backend: Optional[str] = None,
) -> dict[str, Any]:
    """Measure the morph saved in ``dir`` (``deepmorph eval``): ``metrics.json``'s dict."""

def warp(
    image: ImageLike,
    field: str,
    amount: float,
    *,
    backend: Optional[str] = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """A synthetic pair: ``(a, flow)``, ``a`` the image warped by ``field`` (``"smooth"``:
    ``amount`` = largest displacement in pixels; ``"rotate"``: degrees at the centre;
    ``"shear"``: columns per row), ``flow`` ``[H, W, 2]`` the true displacement
    ``(drow, dcol)`` from ``a`` to the image (``deepmorph warp``)."""

def defaults(model: str = "rgb", quality: Optional[str] = None) -> dict[str, Any]:
    """The settings a morph starts from: ``config.json``'s ``config`` object."""

def backends() -> list[str]:
    """The backends compiled in that can run here."""
