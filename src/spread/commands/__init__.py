"""The platform's command bodies, one module per command, callable in-process (by the console scripts in
:mod:`spread.cli`, by a study's stages, by a sweep's trials, by notebooks).

| module | command |
|---|---|
| :mod:`~spread.commands.generate` | ``spread-generate`` |
| :mod:`~spread.commands.import_data` | ``spread-import`` |
| :mod:`~spread.commands.export` | ``spread-export`` |
| :mod:`~spread.commands.train` | ``spread-train`` |
| :mod:`~spread.commands.sample` | ``spread-sample`` (``evaluate=true``: a sweep point) |
| :mod:`~spread.commands.evaluate` | ``spread-evaluate`` |
| :mod:`~spread.commands.ablate` | ``spread-ablate`` (the study: :mod:`spread.experiments.ablation`) |
| :mod:`~spread.commands.compare` | ``spread-compare`` (the study: :mod:`spread.experiments.compare`) |
| :mod:`~spread.commands.sweep` | ``spread-sweep`` (the study: :mod:`spread.experiments.sweep`) |
| :mod:`~spread.commands.in_process` | the commands as one object, for a study's stages and a sweep's trials |
| :mod:`~spread.commands.launch` | training stages as their own processes (local, torchrun, srun) |
| :mod:`~spread.commands.common` | what every body shares: the config recorded beside its outputs, a failed run marked |

Each takes the composed ``conf/<command>.yaml`` (:func:`spread.configs.compose`, or the ``DictConfig`` a Hydra app
receives), turns it into the typed record its schema describes (:func:`spread.configs.to_object`), runs it and
logs it (:mod:`spread.tracking`). The ``print_*`` functions are the commands' console summaries.
"""
