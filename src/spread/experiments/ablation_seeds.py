"""``spread-ablate seeds=[0,1,2]``: the ablation once per training seed, and the table across seeds.

Each seed is a whole ablation (:mod:`spread.experiments.ablation`) in ``out_dir/seed<k>/`` whose training,
sampling and evaluation lists end with ``seed=<k>``; all seeds share one dataset (``data.root``, or the
first seed generates ``out_dir/data`` and the others use it). Each seed's stages resume on their own. The seeds
share the stage pools (:mod:`spread.experiments.stage_pool`): every seed's training stages at once
(``train_concurrent`` at a time), then every seed's sample → evaluate chains (``max_concurrent`` at a time).
A re-run with some rows keeps each seed's other finished rows (carried over, as in one ablation).

The table ``out_dir/ablation.{md,csv,tex,png}`` has one row per variant. A cell reads
``mean ± sd (± h)``: the mean over seeds, the sample standard deviation across seeds (n − 1; 0 with one seed)
and h, half the width of the bootstrap interval over scenes averaged over the seeds (each seed's interval is
:mod:`spread.reporting.intervals`'s). The CSV keeps ``<metric>``, ``<metric>_sd``, ``<metric>_lo`` /
``<metric>_hi`` (the seeds' mean bounds) and ``seeds``; the PNG draws the mean with the sd as error bars.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

from spread.experiments.ablation import LABELS, Ablation, AblationResult, AblationSpec, Commands
from spread.experiments.stages import carried_note
from spread.reporting.tables import Column, columns_of, write_tables


@dataclass(frozen=True)
class SeedColumn(Column):
    """A metric column of the seeds table: ``mean ± sd (± bootstrap half-width)``."""

    def cell(self, record: dict, latex: bool = False) -> str:
        text = self.format(record.get(self.key))
        sd = record.get(f"{self.key}_sd")
        if text == "–" or sd is None or self.valid(record.get(self.key)) is None:
            return text
        half = self.half_width(record)
        boot = "" if half is None else f" (± {half:.{self.digits}f})"
        if latex:
            pm = r"$\pm$"
            return rf"{text}\,{{\scriptsize{pm}{sd * self.scale:.{self.digits}f}{boot.replace('±', pm)}}}"
        return f"{text} ± {sd * self.scale:.{self.digits}f}{boot}"


def seed_spec(spec: AblationSpec, seed: int) -> AblationSpec:
    """The ablation of one seed: its own folder, the shared dataset, every list ending with ``seed=<seed>``."""
    tail = [f"seed={seed}"]
    return replace(spec, out_dir=spec.out_dir / f"seed{seed}", data_root=spec.dataset,
                   train=[*spec.train, *tail], sample=[*spec.sample, *tail], evaluate=[*spec.evaluate, *tail],
                   group=f"{spec.group}_seed{seed}" if spec.group else "")


def mean_sd(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    mean = sum(values) / len(values)
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return mean, sd


def settings_across_seeds(records: list[dict]) -> str:
    """The settings in which one row's runs over the seeds differ, besides what the seed changes by design (the
    checkpoint and every ``seed``): ``"sampler (ddim-10, ddim-5)"``; empty when none does."""
    from spread.runtime.fingerprint import differing

    rows = [r.get("settings") or {} for r in records]
    keys = [k for k in differing(rows) if k != "ckpt" and "seed" not in k.rsplit(".", 1)[-1]]
    return "; ".join(f"{k} ({', '.join(sorted({str(r.get(k)) for r in rows}))})" for k in keys)


def differ_note(rows: list[dict]) -> str:
    """The table's line naming the rows whose seeds' runs differ in a setting (empty when none)."""
    named = [f"{r['method']}: {r['not_averaged']}" for r in rows if r.get("not_averaged")]
    return ("Not averaged (– in the table), as their seeds' runs were made with other settings: " + "; ".join(named)
            + ".") if named else ""


def aggregate(per_seed: dict[int, list[dict]]) -> list[dict]:
    """One record per variant over the seeds' records (module docstring)."""
    variants = [r["variant"] for r in next(iter(per_seed.values()))] if per_seed else []
    rows = []
    metrics = columns_of([r for records in per_seed.values() for r in records])
    for variant in variants:
        mine = [r for records in per_seed.values() for r in records if r["variant"] == variant]
        ok = [r for r in mine if r.get("status") == "ok"]
        row = {"variant": variant, "method": LABELS[variant], "seeds": len(ok),
               "status": "ok" if len(ok) == len(mine) else f"{len(mine) - len(ok)} of {len(mine)} seeds failed"}
        differ = settings_across_seeds(ok)
        if differ:  # runs made with other settings are never averaged (a seed's row carried over from another run)
            row["not_averaged"] = differ
            row["status"], row["seeds"], ok = f"not averaged: its seeds' runs differ in {differ}", 0, []
        carried = sorted({str(r["carried_from"]) for r in mine if r.get("carried_from")})
        if carried:
            row["carried_from"] = ", ".join(carried)
        for c in metrics:
            values = [float(r[c.key]) for r in ok if isinstance(r.get(c.key), (int, float))]
            row[c.key], row[f"{c.key}_sd"] = mean_sd(values)
            for bound in ("lo", "hi"):
                bounds = [float(r[f"{c.key}_{bound}"]) for r in ok if isinstance(r.get(f"{c.key}_{bound}"), (int, float))]
                if bounds and len(bounds) == len(values):
                    row[f"{c.key}_{bound}"] = sum(bounds) / len(bounds)
        rows.append(row)
    return rows


def write_seed_table(rows: list[dict], stem: Path, seeds: list[int], title: str = "") -> dict[str, Path]:
    from spread.reporting.plots import ablation_bars

    metrics = columns_of(rows)
    columns = [Column("method", "Method"),
               *[SeedColumn(**{f.name: getattr(c, f.name) for f in fields(c)}) for c in metrics]]
    caption = title or f"Ablation over training seeds {seeds}"
    note = (f"Each cell: mean ± sd across {len(seeds)} training seeds {seeds} (sample sd), then (± h): half the "
            "width of the 95 % bootstrap interval over scenes, averaged over the seeds.")
    note = " ".join(n for n in (note, carried_note(rows), differ_note(rows)) if n)
    paths = write_tables(rows, columns, stem, caption=caption, label="tab:ablation_seeds", note=note,
                         csv_keys=["variant", "method", "seeds", *[k for c in metrics for k in (c.key, f"{c.key}_sd")],
                                   "status", "carried_from"])
    ablation_bars(rows, metrics, stem.with_suffix(".png"), label_key="method", title=caption)
    return {**paths, "png": stem.with_suffix(".png")}


def run_seeded_ablation(spec: AblationSpec, commands: Commands, seeds: list[int], log_table=None,
                        ablations: dict | None = None) -> AblationResult:
    """Every seed's ablation (their stages pooled, module docstring), then the table across seeds in
    ``spec.out_dir``; ``ablations``: seed → its :class:`Ablation`, built (checked) already."""
    from spread.experiments.stage_pool import run_jobs

    started = time.perf_counter()
    ablations = ablations or {seed: Ablation(seed_spec(spec, seed), commands) for seed in seeds}
    for ablation in ablations.values():  # the first seed generates the shared data, the others find it
        ablation.out.mkdir(parents=True, exist_ok=True)
        ablation.engine.attempt("data", ablation.engine.data_stage, [])
    engines = [a.engine for a in ablations.values()]
    phases = max(len(a.training_phases()) for a in ablations.values())
    for k in range(phases):  # every seed's rows of a phase in one pool (base_time after the clocks that size it)
        run_jobs([job for a in ablations.values() for phase in a.training_phases()[k:k + 1]
                  for job in a.engine.train_jobs(phase)], **{**engines[0].train_pool(), "owner": spec.out_dir})
    run_jobs([job for a in ablations.values() for job in a.engine.row_jobs(list(a.spec.variants))],
             **{**engines[0].row_pool(), "owner": spec.out_dir})
    per_seed, stages, errors = {}, {}, {}
    for seed, ablation in ablations.items():
        result = ablation.finish(None, started)
        per_seed[seed] = result.records
        stages.update({f"seed{seed}/{k}": v for k, v in result.stages.items()})
        errors.update({f"seed{seed}/{k}": v for k, v in result.errors.items()})
    rows = aggregate(per_seed)
    stem = spec.out_dir / "ablation"
    tables = write_seed_table(rows, stem, list(seeds), spec.title)
    if log_table is not None:
        log_table(rows, tables["png"])
    return AblationResult(rows, stages, errors, tables, round(time.perf_counter() - started, 3))
