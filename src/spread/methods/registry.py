"""The method registry: SPREAD and every baseline defined once, with what training, sampling and Table 1 need.

A :class:`MethodSpec` is a method's name (``spread-compare methods=[...]``, a checkpoint's ``method``
hyper-parameter), its LightningModule (``"module:Class"``, loaded on demand), its row label and caption note, how it
samples (``sampling``: ``pipeline`` — the one denoising loop, :func:`spread.model.diffusion.denoise`, driven by
:class:`~spread.sampling.ScenePipeline` with its callbacks (guidance), the module giving ``denoising(batch)`` (SPREAD,
DiffuScene, InstructScene, the release's network) — or ``own``: the module's ``sample``, as ATISS's autoregressive
loop), whether it sees the relation graph (GRecall is reported only then), which trained checkpoint it samples
(``checkpoint``: PhyScene samples DiffuScene's), its own sampling overrides (``sample``: PhyScene's
``guidance=physcene``, SPREAD's ``guidance=refine``) and its training recipes (``train``: the paper-size
experiment's overrides, ``train_quick``: the CPU one) — the one place they live: ``spread-compare`` takes each
method's recipe from here (``recipe=full`` or ``quick``, :meth:`MethodSpec.recipe`) unless its config names a
list for that method. ``spread-compare``, ``spread-sample`` and checkpoint loading iterate :data:`METHODS`.

The built-ins are registered at this module's end, each by its ``"module:Class"`` (a study plans and refuses without
importing Lightning, ~7 s of CPU); another package adds a method through the entry-point group ``spread.methods`` naming a :class:`MethodSpec` (or a LightningModule class, which becomes a
``pipeline`` or ``own`` method by whether it has ``denoising``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from spread.registry import Registry, RegistryError, resolve

SAMPLING = ("pipeline", "own")
#: The sampling settings a method may declare it does not read (:attr:`MethodSpec.ignores`).
IGNORABLE = ("sampler", "graph_scale", "precision")


@dataclass(frozen=True)
class MethodSpec:
    """One method (module docstring). target: ``"module:Class"`` of its LightningModule (or the class itself)."""

    name: str
    target: object
    label: str = ""
    note: str = ""
    sampling: str = "pipeline"
    graph_conditioned: bool = False
    checkpoint: str | None = None
    train: tuple[str, ...] = ()
    train_quick: tuple[str, ...] = ()
    sample: tuple[str, ...] = ()
    #: False: no training recipe here (the authors' weights): its checkpoint must be given (``train.ckpt.<m>``)
    trainable: bool = True
    order: int = 100
    extras: dict = field(default_factory=dict)
    #: The sampling settings (``SamplingConfig`` keys) this method's samples do not depend on, each with the value
    #: its runs record instead (their identity, their ``sampler`` label:
    #: :func:`spread.runtime.fingerprint.unread_sampling`), declared by the method, never inferred (a plug-in's own
    #: loop may read the sampler it is handed): ATISS's own loop reads no ``sampler`` (recorded as what it runs,
    #: ``"one pass per object"``), ``graph_scale`` or ``precision``. Two runs that differ only there are one identity.
    ignores: dict = field(default_factory=dict)
    #: Guidance modes this method runs as another (asked → run), declared by the method: the authors' network runs
    #: the paper's guidance as the authors' refinement (``{"paper": "release"}``). Its samples, identity, labels and
    #: tags are those of the mode it runs (:meth:`guidance_run`), so the two spellings are one run.
    guidance_modes: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.sampling not in SAMPLING:
            raise RegistryError(f"method '{self.name}': sampling={self.sampling!r}, choose from {SAMPLING}")
        unknown = sorted(set(self.ignores) - set(IGNORABLE))
        if unknown:
            raise RegistryError(f"method '{self.name}': ignores={unknown}: a method may declare it ignores only "
                                f"{list(IGNORABLE)}")

    def guidance_run(self, guidance):
        """The :class:`~spread.guidance.GuidanceConfig` this method runs for ``guidance`` (:attr:`guidance_modes`; a
        mode that is none is refused by the config, naming the modes)."""
        import dataclasses

        mode = self.guidance_modes.get(getattr(guidance, "mode", None))
        return guidance if mode is None or not guidance.active else dataclasses.replace(guidance, mode=mode)

    def recipe(self, name: str = "full") -> tuple[str, ...]:
        """The ``spread-train`` overrides of a training recipe: ``full`` (:attr:`train`) or ``quick``
        (:attr:`train_quick`)."""
        recipes = {"full": self.train, "quick": self.train_quick}
        if name not in recipes:
            raise RegistryError(f"method '{self.name}': recipe={name!r}, choose from {list(recipes)}")
        return recipes[name]

    @property
    def trained_from(self) -> str:
        """The method whose trained checkpoint this one samples (itself unless it derives from another)."""
        return self.checkpoint or self.name

    @property
    def row_label(self) -> str:
        return self.label or self.name

    def module_class(self):
        """The LightningModule class (imported on first use)."""
        return resolve(self.target)


def _adapt(name: str, obj) -> MethodSpec:
    if isinstance(obj, MethodSpec):
        return obj if obj.name == name else MethodSpec(**{**obj.__dict__, "name": name})
    if isinstance(obj, type):
        sampling = "pipeline" if hasattr(obj, "denoising") else "own"
        return MethodSpec(name, obj, label=name, sampling=sampling,
                          graph_conditioned=bool(getattr(obj, "graph_conditioned", False)))
    raise RegistryError(f"method entry point '{name}': expected a MethodSpec or a LightningModule class, got {obj!r}")


METHODS: Registry[MethodSpec] = Registry("method", "spread.methods", adapt=_adapt)  # the built-ins: below


def register_method(spec: MethodSpec) -> MethodSpec:
    return METHODS.register(spec.name, spec, origin=str(spec.target))


def method_spec(name: str) -> MethodSpec:
    return METHODS.get(name)


def method_names() -> list[str]:
    """Every registered method in Table 1's row order (baselines, then SPREAD, then plugins)."""
    return [s.name for s in sorted((s for _, s in METHODS.items()), key=lambda s: s.order)]


# The built-ins, each module imported when its class is first asked for (``module_class``): listing them here, not
# in their modules, keeps a study's planning and its refusals free of Lightning's import (~7 s of CPU).
register_method(MethodSpec(
    "atiss", "spread.methods.atiss:ATISS", label="ATISS", note="autoregressive, no graph", sampling="own",
    ignores={"sampler": "one pass per object", "graph_scale": 1.0, "precision": "32"},
    train=("experiment=atiss",), train_quick=("experiment=atiss_quick",), order=10))
register_method(MethodSpec(
    "diffuscene", "spread.methods.diffuscene:DiffuScene", label="DiffuScene", note="DDPM over slots, no graph",
    ignores={"graph_scale": 1.0}, train=("experiment=diffuscene",), train_quick=("experiment=diffuscene_quick",), order=20))
register_method(MethodSpec(
    "physcene", "spread.methods.diffuscene:DiffuScene", label="DiffuScene + PhyScene guidance",
    note="DiffuScene + oriented box-IoU guidance", checkpoint="diffuscene", ignores={"graph_scale": 1.0}, sample=("guidance=physcene",), order=30))
register_method(MethodSpec(
    "instructscene", "spread.methods.instructscene:InstructScene", label="InstructScene (graph-to-layout)",
    note="SPREAD's graph denoiser without shape tokens, geometry or the physical graph", graph_conditioned=True,
    train=("experiment=instructscene",), train_quick=("experiment=instructscene_quick",), order=40))
register_method(MethodSpec(
    "spread", "spread.model.module:SceneDiffusion", label="SPREAD (ours)", note="the platform's SceneDiffusion",
    graph_conditioned=True, train=("experiment=paper_geometry",), train_quick=("experiment=quick", "model.variant=geometry"),
    sample=("guidance=refine",), order=50))
register_method(MethodSpec(
    "release", "spread.methods.release:ReleaseDiffusion", label="SPREAD (authors' weights)",
    note="the release's network and checkpoint (spread-release-ckpt out=)", graph_conditioned=True,
    trainable=False, order=60, guidance_modes={"paper": "release"}))
