"""The configuration: the ``conf/`` folder, the structured-config schemas registered once, and ``compose``.

Every library object's settings are a dataclass with its defaults, in the package that uses them. This
module registers them with Hydra's ConfigStore, so that the YAML files only choose and override (DESIGN
§5, "a default lives once"):

* **group bases** — a group's YAML files start with ``defaults: [base, _self_]`` and override a few keys:
  ``guidance/base`` = :class:`~spread.guidance.GuidanceConfig`, ``sampler/base`` =
  :class:`~spread.model.Sampler`, ``model/base`` = :class:`~spread.model.config.SceneDiffusionConfig` (with
  :class:`~spread.model.config.ModelConfig`: the paper's network), ``protocol/base`` =
  :class:`~spread.evaluation.EvalProtocol`, ``fid/base`` = :class:`~spread.evaluation.FIDConfig`,
  ``ray/base`` = :class:`~spread.runtime.RaySettings`, ``logger/base`` = :class:`~spread.tracking.config.LoggerConfig`,
  ``paths/base`` = :class:`PathsConfig`;
* **command schemas** — a command's primary config (``conf/<command>.yaml``) starts with its schema, the
  library record it fills plus the command's own keys: ``generate_schema`` = :class:`GenerateCommand`
  (:class:`~spread.procgen.dataset.DatasetConfig`), ``sample_schema`` = :class:`SampleCommand`
  (:class:`~spread.sampling.SamplingConfig`), ``evaluate_schema`` = :class:`EvaluateCommand`
  (:class:`~spread.evaluation.EvaluationConfig`), ``import_schema`` = ``ImportCommand``
  (:class:`~spread.importers.run.ImportConfig`), ``export_schema`` = ``ExportCommand``
  (:class:`~spread.export.ExportConfig`). ``OmegaConf.to_object(cfg)`` then *is* the library record,
  typed and validated — no field is copied by hand. ``spread-train`` instantiates its ``_target_`` nodes.

Registration is per command (:func:`register`), so a light command (``spread-generate``) does not import
torch to register the model's schema. The command schemas built on demand are still module attributes
(``spread.configs.ImportCommand`` etc., made by :func:`__getattr__`), so their instances pickle by name: a
spawn pool or a Ray worker can receive them.
"""


import functools
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import MISSING, DictConfig, OmegaConf

#: The commands whose schemas :func:`register` knows, and the config groups each one composes.
COMMANDS = ("generate", "import", "export", "train", "sample", "evaluate", "ablate", "compare", "report")


def conf_dir() -> str:
    """Absolute path of the Hydra config folder (the repository's ``conf/``, or ``$SPREAD_CONF_DIR``)."""
    env = os.environ.get("SPREAD_CONF_DIR")
    if env:
        return str(Path(env).resolve())
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "conf" / "generate.yaml").exists():
            return str(parent / "conf")
    raise FileNotFoundError("cannot find the conf/ folder; set SPREAD_CONF_DIR to the repository's conf/")


@dataclass
class PathsConfig:
    """runs_dir: where run folders go (relative paths: to the directory the command runs in)."""

    runs_dir: str = "runs"


def _store(group: str | None, name: str, node) -> None:
    """Store ``node`` once per process (a schema is a fixed dataclass; storing it again re-builds its OmegaConf
    node, a good part of a :func:`compose`'s time)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    where = store.repo.get(group, {}) if group else store.repo
    if f"{name}.yaml" in where:
        return
    store.store(group=group, name=name, node=node)


def _common() -> None:
    from spread.runtime.ray import RaySettings
    from spread.tracking.loggers import LoggerConfig

    _store("paths", "base", PathsConfig)
    _store("ray", "base", RaySettings)
    _store("logger", "base", LoggerConfig)


def _generate() -> None:
    _store(None, "generate_schema", GenerateCommand())


def _model() -> None:
    from spread.guidance.config import GuidanceConfig
    from spread.model.config import SceneDiffusionConfig
    from spread.model.sampler import Sampler

    _store("model", "base", SceneDiffusionConfig)
    _store("sampler", "base", Sampler)
    _store("guidance", "base", GuidanceConfig)


def _evaluation() -> None:
    from spread.evaluation.protocol import EvalProtocol, FIDConfig

    _store("protocol", "base", EvalProtocol)
    _store("fid", "base", FIDConfig)


def register_resolvers() -> None:
    """``${point_fp:}`` (the short point fingerprint: :func:`spread.runtime.fingerprint.point_short`),
    ``${point_dir:<sweep folder>/<values>}`` (a point's run folder: :func:`spread.runtime.fingerprint.point_dir`),
    ``${launch_id:}`` (unique per launching process) and ``${wandb_mode:}``
    (:func:`spread.tracking.config.wandb_mode`)."""
    from omegaconf import OmegaConf

    from spread.runtime.fingerprint import launch_id, point_dir, point_short
    from spread.tracking.config import wandb_mode

    if not OmegaConf.has_resolver("point_fp"):
        OmegaConf.register_new_resolver("point_fp", point_short, use_cache=False)
    if not OmegaConf.has_resolver("point_dir"):
        OmegaConf.register_new_resolver("point_dir", point_dir, use_cache=False)
    if not OmegaConf.has_resolver("launch_id"):
        OmegaConf.register_new_resolver("launch_id", launch_id)
    if not OmegaConf.has_resolver("wandb_mode"):
        OmegaConf.register_new_resolver("wandb_mode", wandb_mode, use_cache=False)


def register(*commands: str) -> None:
    """Register the schemas the ``commands`` compose (all of :data:`COMMANDS` when none is named)."""
    for name in commands or COMMANDS:
        if name not in COMMANDS:
            raise ValueError(f"unknown command '{name}' (known: {COMMANDS})")
    wanted = set(commands or COMMANDS)
    register_resolvers()
    _common()
    if wanted & {"generate", "ablate", "compare"}:
        _generate()
    if "import" in wanted:
        _store(None, "import_schema", import_command())
    if "export" in wanted:
        _store(None, "export_schema", export_command())
    if wanted & {"train", "sample", "ablate", "compare"}:
        _model()
    if wanted & {"sample", "evaluate", "ablate", "compare"}:
        _evaluation()
    if wanted & {"sample", "ablate", "compare"}:
        _store(None, "sample_schema", sample_command())
    if wanted & {"evaluate", "ablate", "compare"}:
        _store(None, "evaluate_schema", evaluate_command())


#: Composed configs by what they are composed from (:func:`compose`); copies are handed out, never these.
_COMPOSED: dict = {}


def _conf_signature(folder: str) -> tuple:
    """Every file of the config folder by (path, size, mtime): a file edited in this process composes anew."""
    out = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            stat = os.stat(os.path.join(root, name))
            out.append((root, name, stat.st_size, stat.st_mtime_ns))
    return tuple(out)


def _search_path() -> tuple | None:
    """The running Hydra app's config sources (None outside one): another app composes from other folders."""
    from hydra.core.global_hydra import GlobalHydra

    hydra = GlobalHydra.instance()
    if not hydra.is_initialized():
        return None
    return tuple((s.provider, s.path) for s in hydra.config_loader().get_sources())


def compose(name: str, overrides: list[str] | tuple[str, ...] = ()) -> DictConfig:
    """``conf/<name>.yaml`` composed with ``overrides`` (inside a running Hydra app or not).

    Composing is ~0.1 s and a study's planning composes each stage's config more than once (its identity, its
    checks, its command): the result is kept per (name, overrides, config folder and its files' sizes and times,
    the running app's config sources) and each call gets its own copy (~2 ms) to change as it likes. Overrides
    that add config sources (``hydra.searchpath``) compose every time."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register(name) if name in COMMANDS else register()
    overrides = [str(o) for o in overrides]
    search = _search_path()
    key = None
    if not any(o.lstrip("+~").startswith("hydra.searchpath") for o in overrides):
        key = (name, tuple(overrides), conf_dir(), _conf_signature(conf_dir()), search)
        if key in _COMPOSED:
            return _fresh_copy(_COMPOSED[key])
    if search is not None:
        composed = hydra_compose(config_name=name, overrides=overrides)
    else:
        with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
            composed = hydra_compose(config_name=name, overrides=overrides)
    if key is None:
        return composed
    if len(_COMPOSED) >= 512:
        _COMPOSED.clear()
    _COMPOSED[key] = composed
    return _fresh_copy(composed)


def _fresh_copy(composed: DictConfig) -> DictConfig:
    """A caller's own copy of a kept config, without the resolver values cached while it was composed (Hydra's
    ``${now:...}``: each copy resolves the time when it is read)."""
    import copy

    out = copy.deepcopy(composed)
    OmegaConf.clear_cache(out)
    return out


def error_message(error: BaseException) -> str:
    """A user error's message on one line; Hydra's composition errors with the first line of their cause (``Value
    'abc' could not be converted to Float``, ``Key 'colision' not in 'GuidanceConfig'``), which says what was
    wrong with the override, and without Hydra's list of config sources; a required setting (``???``) left
    unset as ``<key> is required``."""
    from hydra.errors import ConfigCompositionException
    from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue

    if isinstance(error, (MissingMandatoryValue, InterpolationToMissingValueError)):
        key = getattr(error, "full_key", None)
        if isinstance(error, InterpolationToMissingValueError):  # ${out_dir} read while out_dir is ???
            found = re.search(r"Missing mandatory value: ([\w.\[\]-]+)", str(error))
            key = found.group(1) if found else None
        if key:
            return required_message([key])
    text = str(error).split("\nConfig search path:")[0]  # a missing config group option: the options, not the paths
    message = " ".join(text.split()) or type(error).__name__
    inner = error.__cause__
    if isinstance(error, ConfigCompositionException) and inner is not None and str(inner).strip():
        message += f" ({str(inner).strip().splitlines()[0]})"
    return message


def required_message(keys, hint: str = "") -> str:
    """One line naming required settings (``???`` in the config) that the command line left unset; ``hint``: where
    to read what they are."""
    keys = sorted(keys)
    given = " ".join(f"{k}=..." for k in keys)
    return (f"required setting{'s' if len(keys) > 1 else ''} not given: {', '.join(keys)} (add {given}"
            + (f"; {hint}" if hint else "") + ")")


def to_object(cfg: DictConfig):
    """A composed config as its schema's dataclass (nested records included), validated."""
    return OmegaConf.to_object(cfg)


def model_config(name: str = "tiny", **fields):
    """The :class:`~spread.model.config.ModelConfig` of ``conf/model/<name>.yaml`` with ``fields`` replaced,
    e.g. for a test or benchmark that builds a ``tiny`` model without a command."""
    from spread.model.config import ModelConfig

    cfg = compose("train", [f"model={name}", "data.root=/unused"])
    return ModelConfig.from_any(OmegaConf.to_container(cfg.model.config, resolve=True), **fields)


# ---- command schemas --------------------------------------------------------------------------------------

from spread.procgen.dataset import DatasetConfig  # noqa: E402  (light: no torch)


@dataclass
class GenerateCommand(DatasetConfig):
    """``spread-generate``: the dataset's settings plus out_dir (the dataset folder) and progress."""

    out_dir: str = MISSING
    progress: bool = True
    paths: PathsConfig = field(default_factory=PathsConfig)


@functools.cache
def sample_command():
    """The ``spread-sample`` schema: :class:`~spread.sampling.SamplingConfig` plus the command's logger,
    wandb group and tags, and ``evaluate=true``'s evaluation settings (defined here because it joins two
    stages; built on demand so that importing this module stays light)."""
    from spread.evaluation.protocol import EvalProtocol, FIDConfig
    from spread.metrics.registry import default_metric_names
    from spread.tracking.loggers import LoggerConfig
    from spread.sampling.run import SamplingConfig

    @dataclass
    class EvaluateAfterSampling:
        """``spread-sample evaluate=true``: evaluate ``out_dir/scenes`` against ``reference_split`` of the
        dataset, results beside them (the scenes renders are already there, so none by default)."""

        reference_split: str = "${data.split}"
        #: registered metrics by name (``spread.metrics.registry``; default the four of DESIGN §6), read by
        #: ``evaluation.protocol.metrics`` (conf/sample.yaml)
        metrics: list[str] = field(default_factory=default_metric_names)
        chunk_size: int = 4
        renders: int = 0
        retry_failed: bool = False
        protocol: EvalProtocol = field(default_factory=EvalProtocol)
        fid: FIDConfig = field(default_factory=FIDConfig)

        def __post_init__(self) -> None:  # refused when the command starts, not after the sampling
            from spread.checks import whole_number

            for key, least in (("chunk_size", 1), ("renders", 0)):
                whole_number(getattr(self, key), f"evaluation.{key}", least)

    _public(EvaluateAfterSampling)

    @dataclass
    class SampleCommand(SamplingConfig):
        logger: LoggerConfig = field(default_factory=LoggerConfig)
        experiment_name: str = "sample"
        tags: list[str] = field(default_factory=list)
        evaluate: bool = False
        evaluation: EvaluateAfterSampling = field(default_factory=EvaluateAfterSampling)
        sweep_dir: str | None = None
        paths: PathsConfig = field(default_factory=PathsConfig)

    return _public(SampleCommand)


@functools.cache
def evaluate_command():
    """The ``spread-evaluate`` schema: :class:`~spread.evaluation.EvaluationConfig` plus the command's seed
    (the protocol's), logger and wandb group."""
    from spread.evaluation.run import EvaluationConfig
    from spread.metrics.registry import default_metric_names
    from spread.tracking.loggers import LoggerConfig

    @dataclass
    class EvaluateCommand(EvaluationConfig):
        seed: int = 0
        #: registered metrics by name (``spread.metrics.registry``, plugins included), read by
        #: ``protocol.metrics`` (conf/evaluate.yaml); default the four of DESIGN §6
        metrics: list[str] = field(default_factory=default_metric_names)
        logger: LoggerConfig = field(default_factory=LoggerConfig)
        experiment_name: str = "evaluate"
        paths: PathsConfig = field(default_factory=PathsConfig)

    return _public(EvaluateCommand)


def _with_paths(base: type, name: str) -> type:
    """``base`` (a library record whose fields are a command's keys) plus the run-folder ``paths``."""
    from dataclasses import make_dataclass

    return _public(make_dataclass(name, [("paths", PathsConfig, field(default_factory=PathsConfig))], bases=(base,)))


@functools.cache
def import_command():
    """The ``spread-import`` schema: :class:`~spread.importers.run.ImportConfig` plus the run-folder paths."""
    from spread.importers.run import ImportConfig

    return _with_paths(ImportConfig, "ImportCommand")


@functools.cache
def export_command():
    """The ``spread-export`` schema: :class:`~spread.export.ExportConfig` plus the run-folder paths."""
    from spread.export import ExportConfig

    return _with_paths(ExportConfig, "ExportCommand")


def _public(cls: type) -> type:
    """``cls`` (a schema built inside a function) named as an attribute of this module, so that pickle finds
    it by ``spread.configs.<name>`` (:func:`__getattr__` builds it on first lookup in another process)."""
    cls.__module__ = __name__
    cls.__qualname__ = cls.__name__
    return cls


#: Schemas built on demand, by name → the function that builds them (for pickle's lookup by name).
_ON_DEMAND = {"ImportCommand": "import_command", "ExportCommand": "export_command",
              "SampleCommand": "sample_command", "EvaluateCommand": "evaluate_command",
              "EvaluateAfterSampling": "sample_command"}


def __getattr__(name: str):
    if name in _ON_DEMAND:
        made = globals()[_ON_DEMAND[name]]()
        if name == "EvaluateAfterSampling":
            return made.__dataclass_fields__["evaluation"].default_factory
        return made
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
