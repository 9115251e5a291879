"""``spread-sample ckpt=PATH data.root=DIR out_dir=OUT``: a checkpoint + test graphs → scene files (DESIGN §5).

The work is :func:`spread.sampling.run_sampling`; this file turns the Hydra config into its arguments
and prints a summary.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir


def sampling_config(cfg: DictConfig):
    """The :class:`~spread.sampling.SamplingConfig` of a composed ``conf/sample.yaml``."""
    from spread.distributed import RaySettings
    from spread.sampling import SamplingConfig

    ray = OmegaConf.to_container(cfg.ray, resolve=True)
    gpus = float(ray.pop("num_gpus_per_worker", 0) or 0)
    try:
        return SamplingConfig(
            ckpt=str(cfg.ckpt), data_root=str(cfg.data.root), split=str(cfg.data.split), out_dir=str(cfg.out_dir),
            sampler=OmegaConf.to_container(cfg.sampler, resolve=True), samples_per_graph=int(cfg.samples_per_graph),
            seed=int(cfg.seed), batch_size=int(cfg.batch_size), workers=int(cfg.workers), device=str(cfg.device),
            threads=None if cfg.threads is None else int(cfg.threads), use_ema=bool(cfg.use_ema),
            graph_scale=float(cfg.graph_scale), resume=bool(cfg.resume), renders=int(cfg.renders),
            progress=bool(cfg.progress), num_gpus_per_worker=gpus, ray=RaySettings(**ray))
    except TypeError as exc:  # an unknown key under ray/sampler
        raise SystemExit(f"spread-sample: bad config: {exc}") from exc


@hydra.main(config_path=conf_dir(), config_name="sample", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.sampling import run_sampling

    result = run_sampling(sampling_config(cfg))
    m = result.manifest
    per_batch = "" if m["seconds_per_batch"] is None else f", {m['seconds_per_batch']:.2f} s per batch"
    print(f"{result.out_dir / 'scenes'}: {m['samples']} scenes of {m['graphs']} graphs "
          f"({m['written_this_run']} written now, {m['resumed']} already there; {m['seconds']:.1f} s{per_batch}; "
          f"{m['runner']['mode']}, {m['runner']['workers']} worker(s))")


if __name__ == "__main__":
    main()
