"""The Python API: the pipeline of ``byoc register`` with numpy in and out.

``from byoc_cli import register, extract_features, load_weights, load_cloud, Registrar``.
The functions take ``(N, 3)`` arrays (metres) or file paths, use the same recipe as the CLI
(:data:`byoc_cli.pipeline.recipe.PRESETS`, or a ``recipe=``) and give the same results
for the same seed: the ``byoc register``, ``register-batch`` and ``features`` commands are
built on them. Results are NamedTuples of numpy arrays and numbers. Errors are the typed
errors of :mod:`byoc_cli.errors`.

torch and the encoder are imported when a function is first called, not on import.

Threads: importing this module before torch is imported applies the tool's thread policy
(:mod:`byoc_cli.threads`): it puts ``OMP_WAIT_POLICY=PASSIVE`` and ``OMP_NUM_THREADS`` (the
cores the process may use: affinity and cgroup quota) into ``os.environ`` unless they are
set, so that torch starts with them. When torch is already imported nothing is changed.
A :class:`Registrar` runs its work on ``threads`` worker threads (default: torch's thread
count) with one torch thread each: the two clouds of a pair are read, encoded and
prepared side by side, and :meth:`Registrar.executor` lets callers run pairs side by side.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

from byoc_cli.threads import apply_thread_policy

if "torch" not in sys.modules:  # only before torch: OpenMP reads its settings when loaded
    apply_thread_policy()

from byoc_cli.pipeline.inputs import DEPTH_EXTENSIONS, load_cloud, load_weights
from byoc_cli.pipeline.registrar import Registrar
from byoc_cli.pipeline.results import Features, Registration

if TYPE_CHECKING:
    from byoc_cli.pipeline.recipe import RegistrationRecipe

__all__ = [
    "DEPTH_EXTENSIONS",
    "Features",
    "Registrar",
    "Registration",
    "extract_features",
    "load_cloud",
    "load_weights",
    "register",
]


def extract_features(
    cloud: Any,
    *,
    recipe: RegistrationRecipe | None = None,
    device: str = "auto",
    **overrides: Any,
) -> Features:
    """Per-point features of one cloud (``(N, 3)`` metres or a file); see :class:`Features`.

    ``recipe``, ``device`` and the overrides ``features``, ``weights``, ``voxel_size``: see
    :class:`Registrar`; ``scale``, ``intrinsics``, ``depth_scale``: see
    :meth:`Registrar.extract`. For many clouds build one :class:`Registrar` (the weights are
    loaded once).

    Raises:
        TypeError: an unknown keyword.
    """
    unknown = set(overrides) - {*_REGISTRAR_KEYS, *_LOAD_KEYS} - {"fallback"}
    if unknown:
        raise TypeError(f"extract_features() got unexpected keyword(s) {sorted(unknown)}")
    made = {k: overrides[k] for k in ("features", "weights", "voxel_size") if k in overrides}
    registrar = Registrar(device=device, recipe=recipe, **made)
    return registrar.extract(cloud, **{k: overrides[k] for k in _LOAD_KEYS if k in overrides})


#: :func:`register`'s keywords that go to :class:`Registrar`, to :meth:`Registrar.register`
#: (the clouds' units) and to :meth:`Registrar.match`
_REGISTRAR_KEYS = ("features", "weights", "voxel_size", "fallback")
_LOAD_KEYS = ("scale", "intrinsics", "depth_scale")
_MATCH_KEYS = ("estimator", "refine", "max_points", "num_correspondences", "seed")
#: :func:`register`'s keywords of a registration from an initial pose
_INIT_KEYS = ("init", "max_correction", "init_mode")


def register(
    source: Any,
    target: Any,
    *,
    recipe: RegistrationRecipe | None = None,
    device: str = "auto",
    **overrides: Any,
) -> Registration:
    """Register ``source`` onto ``target`` as ``byoc register`` does (same recipe, same T).

    Args:
        source, target: ``(N, 3)`` arrays in metres, or point-cloud / depth-image files.
        recipe: the :class:`~byoc_cli.pipeline.recipe.RegistrationRecipe` (None: the preset
            of ``features``, the learned features' without it).
        device: see :class:`Registrar`.
        overrides: keywords that change the recipe or say how to read the inputs:
            ``features``, ``weights``, ``voxel_size``, ``fallback`` (see :class:`Registrar`);
            ``estimator``, ``refine``, ``max_points``, ``num_correspondences``, ``seed`` (see
            :meth:`Registrar.match`); ``scale`` (multiply the inputs by this, 0.001 for
            millimetres; T is in the input units), ``intrinsics``, ``depth_scale`` (for
            depth-image files); ``init`` (a ``(4, 4)`` guess of ``T_tgt_src`` in the input
            units: the local registration from it), ``max_correction`` (``(degrees,
            distance)``: its trust region) and ``init_mode`` (``"local"``, or ``"global"``: the
            global registration checked against the guess; see :meth:`Registrar.register`).

    Returns:
        :class:`Registration`.

    Raises:
        InputError, ShapeError, WeightsError, RegistrationError: see :class:`Registrar`.
        TypeError: an unknown keyword.
        ValueError: ``init`` is not a rigid 4x4 transform, a bad ``max_correction`` or
            ``init_mode``.
    """
    unknown = set(overrides) - {*_REGISTRAR_KEYS, *_LOAD_KEYS, *_MATCH_KEYS, *_INIT_KEYS}
    if unknown:
        raise TypeError(f"register() got unexpected keyword(s) {sorted(unknown)}")
    made = {k: overrides[k] for k in _REGISTRAR_KEYS if k in overrides}
    registrar = Registrar(device=device, recipe=recipe, **made)
    return registrar.register(
        source,
        target,
        **{k: overrides[k] for k in _LOAD_KEYS if k in overrides},
        **{k: overrides[k] for k in (*_MATCH_KEYS, *_INIT_KEYS) if k in overrides},
    )
