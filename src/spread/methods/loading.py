"""Loading any method's checkpoint (SPREAD's SceneDiffusion, the release's network, every baseline, a plugin's) by the
``method`` hyperparameter it saved, through the registry (:mod:`spread.methods.registry`); weights-only reading
(:func:`spread.safe_load.load_checkpoint`), shapes checked on PyTorch's ``meta`` device before allocating."""

from __future__ import annotations

from spread.methods.registry import method_names, method_spec


def graph_conditioned() -> tuple[str, ...]:
    """Methods that condition on the relation graph (GRecall is meaningful for them), from the registry."""
    return tuple(name for name in method_names() if method_spec(name).graph_conditioned)


def module_class(method: str):
    """The LightningModule class of a registered method name (:data:`METHODS`; plugins included)."""
    return method_spec(method).module_class()


def checkpoint_method(hparams: dict) -> str:
    """The method a checkpoint's hyperparameters belong to (:func:`spread.safe_load.checkpoint_identity`: no
    ``method`` key is SceneDiffusion)."""
    from spread.safe_load import checkpoint_identity

    return checkpoint_identity({"hyper_parameters": hparams})["method"]


def meta_module(cls, checkpoint: dict, source: str = "checkpoint"):
    """The module a checkpoint's hyperparameters build, on PyTorch's ``meta`` device (no memory, no weights loaded),
    or None when the class cannot be built there (as saved first; then without bounds: the platform's set_bounds
    reads values, which meta tensors lack). A :class:`spread.safe_load.CheckpointMismatchError` is raised as is, and
    so is the class's refusal of a hyperparameter (a ``ValueError`` both ways: ``nearest: bogus``, ``prediction:
    bogus``), naming ``source``: the module would refuse it as well, after the command had started its work."""
    import torch

    from spread.safe_load import CheckpointMismatchError

    hp = dict(checkpoint.get("hyper_parameters") or {})
    refused = None
    for attempt in (hp, {**hp, "bounds": None} if "bounds" in hp else None):
        if attempt is None:
            continue
        try:
            with torch.device("meta"):
                return cls(**attempt)
        except CheckpointMismatchError:
            raise
        except ValueError as exc:
            refused = exc
        except Exception:  # noqa: BLE001 - not buildable on meta this way
            refused = None
            continue
    if refused is not None:
        raise CheckpointMismatchError(f"{source}: its hyperparameters do not build the '{checkpoint_method(hp)}' "
                                      f"network: {refused}") from None
    return None


def weight_problem(name: str, value) -> str | None:
    """Why a checkpoint's tensor ``name`` cannot be a trained weight, or None: it has no values (PyTorch's ``meta``
    device), it is a view larger than the storage it reads (a stride-0 ``expand``: a 1.6 kB file asked for 40 TB
    when read in full), or it holds NaN or infinity (a diverged run's weights sample NaN poses)."""
    import torch

    if not isinstance(value, torch.Tensor):
        return None
    problem = storage_problem(name, value)
    if problem:
        return problem
    if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
        return f"weight '{name}' holds non-finite values (NaN or infinity)"
    return None


def storage_problem(name: str, value) -> str | None:
    """Why tensor ``name`` holds no values of its own to read, or None: on PyTorch's ``meta`` device, or a view that
    reads more bytes than its storage has (a stride-0 ``expand``: any op over it allocates its full size)."""
    if value.is_meta:
        return f"weight '{name}' is on PyTorch's meta device: it holds no values"
    if value.numel() and value.untyped_storage().nbytes() < value.numel() * value.element_size():
        return (f"weight '{name}' of shape {tuple(value.shape)} reads {value.numel() * value.element_size():,} bytes "
                f"from a storage of {value.untyped_storage().nbytes():,} (an expanded or overlapping view)")
    return None


def check_weight_shapes(cls, checkpoint: dict, source: str = "checkpoint"):
    """Before a network is allocated from a checkpoint's hyperparameters: build it on PyTorch's ``meta``
    device (:func:`meta_module`: no memory) and compare the shapes of the weights both have, so a checkpoint whose
    config asks for ``dim=2e6`` (terabytes) or whose weights belong to another size is refused in one line
    (:class:`spread.safe_load.CheckpointMismatchError`); weights made after construction (a baseline's EMA
    copy) are left to the strict ``load_state_dict``. A class that cannot be built on ``meta`` is not checked
    here (its strict ``load_state_dict`` still refuses a mismatch, after allocation). Returns the meta module (None:
    not buildable there), on which settings can be checked against the model before any work."""
    from spread.safe_load import CheckpointMismatchError

    hp = dict(checkpoint.get("hyper_parameters") or {})
    module = meta_module(cls, checkpoint, source)
    if module is None:  # not buildable on meta: leave it to load_state_dict
        return None
    shapes = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    weights = checkpoint.get("state_dict") or {}
    held = {k: tuple(getattr(v, "shape", ())) for k, v in weights.items()}
    for name, shape in shapes.items():
        if name in held and held[name] != shape:
            raise CheckpointMismatchError(
                f"{source}: its hyperparameters build weight '{name}' of shape {shape}, the file holds {held[name]} "
                f"(config {hp.get('config', {})}); hyperparameters and weights disagree, refused before allocating")
    parameters = {name for name, _ in module.named_parameters()}  # not buffers: bounds not yet set are infinite
    for name in sorted(parameters & set(weights)):
        problem = weight_problem(name, weights[name])
        if problem:
            raise CheckpointMismatchError(f"{source}: {problem}; refused before any work")
    if shapes and not set(shapes) & set(held):
        raise CheckpointMismatchError(
            f"{source}: none of its {len(held)} weights belongs to the '{checkpoint_method(hp)}' network its "
            f"hyperparameters describe (first: {sorted(held)[:1]}); refused before allocating")
    return module


def module_from_checkpoint(checkpoint: dict, map_location="cpu", source: str = "checkpoint"):
    """The LightningModule of a checkpoint's dict (read with :func:`spread.safe_load.load_checkpoint`, which
    runs no code), of the class its hyperparameters name: built from them, then its weights (EMA included),
    strictly."""
    cls = module_class(checkpoint_method(checkpoint.get("hyper_parameters") or {}))
    check_weight_shapes(cls, checkpoint, source)
    if hasattr(cls, "from_checkpoint"):
        return cls.from_checkpoint(checkpoint, map_location=map_location)
    model = cls(**checkpoint["hyper_parameters"])
    model.load_state_dict(checkpoint["state_dict"])
    return model.to(map_location)


def load_module(ckpt_path, map_location="cpu"):
    """The LightningModule saved in ``ckpt_path`` (``weights_only`` loading: no code runs from the file)."""
    from spread.safe_load import load_checkpoint

    return module_from_checkpoint(load_checkpoint(ckpt_path), map_location, source=str(ckpt_path))


def trained_identity(model_cfg) -> dict:
    """What a checkpoint trained with this composed ``model`` node (``spread-train``'s ``cfg.model``) will hold, as
    :func:`spread.safe_load.checkpoint_identity` reads it back: ``method``, the registered method whose LightningModule
    ``_target_`` names (None: none registered), and ``variant``, ``model.variant`` where the model has one (SPREAD's
    base / geometry). Asked of the config, not of the override strings: a list that sets ``experiment=quick`` under a
    baseline's name composes SPREAD, and this says so."""
    from omegaconf import OmegaConf

    from spread.registry import resolve

    target = str(OmegaConf.select(model_cfg, "_target_", default=""))
    dotted = target.replace(":", ".")
    names = method_names()
    method = next((n for n in names if isinstance(method_spec(n).target, str)
                   and method_spec(n).target.replace(":", ".") == dotted), None)
    if method is None and target:  # a re-exported path, or a plugin registered with its class
        module, _, attr = dotted.rpartition(".")
        try:
            cls = resolve(f"{module}:{attr}")
        except (ImportError, AttributeError, ValueError):
            cls = None
        method = next((n for n in names if cls is not None and method_spec(n).module_class() is cls), None)
    return {"method": method, "variant": OmegaConf.select(model_cfg, "variant", default=None)}
