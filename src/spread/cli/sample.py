"""``spread-sample ckpt=PATH data.root=DIR out_dir=OUT``: a checkpoint + test graphs → scene files (DESIGN §5).

The work is :func:`spread.sampling.run_sampling`; this file turns the Hydra config into its arguments
and prints a summary. ``guidance=paper|refine`` samples with physics guidance (:mod:`spread.guidance`);
``evaluate=true`` then evaluates ``out_dir/scenes`` (:func:`spread.distributed.run_evaluation`, the protocol
of ``evaluation.protocol``) into ``out_dir/metrics.json`` and ``per_scene.jsonl`` — one run folder per point
of a guidance sweep. With ``logger=wandb`` (offline by default) the run is logged with ``job_type=sample``,
``group=experiment_name``, tags for the variant, sampler and guidance weights, and the full config.
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
            progress=bool(cfg.progress), num_gpus_per_worker=gpus, ray=RaySettings(**ray),
            guidance=OmegaConf.to_container(cfg.guidance, resolve=True))
    except TypeError as exc:  # an unknown key under ray/sampler
        raise SystemExit(f"spread-sample: bad config: {exc}") from exc


def evaluation_config(cfg: DictConfig):
    """The :class:`~spread.distributed.EvaluationConfig` for ``evaluate=true``: the run's scenes against the
    dataset, results beside them in ``out_dir``."""
    from pathlib import Path

    from spread.cli.evaluate import eval_protocol
    from spread.distributed import EvaluationConfig, RaySettings

    ev = cfg.evaluation
    ray = OmegaConf.to_container(cfg.ray, resolve=True)
    ray.pop("num_gpus_per_worker", None)
    try:
        return EvaluationConfig(
            scenes=str(Path(str(cfg.out_dir)) / "scenes"), reference=str(cfg.data.root), out_dir=str(cfg.out_dir),
            reference_split=str(ev.reference_split), chunk_size=int(ev.chunk_size), resume=bool(cfg.resume),
            retry_failed=bool(ev.retry_failed), renders=int(ev.renders), progress=bool(cfg.progress),
            protocol=eval_protocol(ev.protocol, ev.fid, ev.seed), ray=RaySettings(**ray))
    except TypeError as exc:  # an unknown key under evaluation.protocol
        raise SystemExit(f"spread-sample: bad evaluation config: {exc}") from exc


def wandb_tags(cfg: DictConfig, manifest: dict) -> list[str]:
    """Variant, sampler and guidance tags (DESIGN run-comparison conventions), plus ``cfg.tags``."""
    import torch

    from spread.sampling.worker import sampler_label
    from spread.model import Sampler

    # mmap: the hyperparameters only, without reading the weights into memory
    hp = torch.load(str(cfg.ckpt), map_location="cpu", weights_only=False, mmap=True).get("hyper_parameters", {})
    guidance = manifest.get("guidance")
    tags = [str(hp.get("variant") or hp.get("method", "unknown")), sampler_label(Sampler.from_config(
        OmegaConf.to_container(cfg.sampler, resolve=True)))]
    if guidance:
        tags += ["guidance", f"guidance={guidance['mode']}"] + [f"{k}={guidance[k]:g}"
                                                                for k in ("collision", "gravity", "relation")]
    return tags + [str(t) for t in (cfg.tags or [])]


def log_run(cfg: DictConfig, manifest: dict, evaluation=None) -> None:
    """The sampling run (and its evaluation) on wandb, ``job_type=sample``."""
    from spread.distributed.wandb_report import log_sampling

    log_sampling(manifest, out_dir=str(cfg.out_dir), config=OmegaConf.to_container(cfg, resolve=True),
                 mode=str(cfg.logger.mode), project=str(cfg.logger.project), group=str(cfg.experiment_name),
                 name=cfg.logger.run_name, tags=wandb_tags(cfg, manifest), evaluation=evaluation)


@hydra.main(config_path=conf_dir(), config_name="sample", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.sampling import run_sampling

    if cfg.logger.name not in ("wandb", "none"):
        raise SystemExit(f"spread-sample: unknown logger '{cfg.logger.name}' (wandb or none)")
    if cfg.evaluate and cfg.resume:  # a finished sweep point: scenes and metrics are there, leave them be
        from spread.experiments import is_finished_run

        if is_finished_run(cfg.out_dir):
            print(f"{cfg.out_dir}: finished earlier (metrics.json exists), skipped")
            return
    result = run_sampling(sampling_config(cfg))
    evaluation = None
    if cfg.evaluate:
        from spread.cli.evaluate import print_summary
        from spread.distributed import run_evaluation

        evaluation = run_evaluation(evaluation_config(cfg))
        print_summary(evaluation.metrics, evaluation.out_dir)
    if cfg.logger.name == "wandb":
        log_run(cfg, result.manifest, evaluation)
    m = result.manifest
    per_batch = "" if m["seconds_per_batch"] is None else f", {m['seconds_per_batch']:.2f} s per batch"
    print(f"{result.out_dir / 'scenes'}: {m['samples']} scenes of {m['graphs']} graphs "
          f"({m['written_this_run']} written now, {m['resumed']} already there; {m['seconds']:.1f} s{per_batch}; "
          f"{m['runner']['mode']}, {m['runner']['workers']} worker(s))")


if __name__ == "__main__":
    main()
