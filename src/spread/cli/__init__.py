"""Console scripts: one thin ``main`` per command (a Hydra app over ``conf/<command>.yaml``) that calls the
command's library function in :mod:`spread.commands` (or :mod:`spread.experiments` for the
ablation and reports) and prints its summary. Nothing imports this package."""
