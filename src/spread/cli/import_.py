"""``spread-import source=spread_release|threed_front src=DIR out_dir=DIR``: another layout → dataset folder
(:mod:`spread.importers`; ``import`` is a Python keyword, hence the module name)."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-import", config="import")
def main(cfg: DictConfig) -> None:
    from spread.commands.import_data import import_data, print_import_summary

    manifest = import_data(cfg)
    print_import_summary(manifest, cfg.out_dir)
    if not sum(manifest["counts"].values()):  # the summary says why; a dataset of no room is no success
        first = (manifest["errors"]["rooms"] or [{}])[0]
        raise SystemExit(f"spread-import: no room was imported ({manifest['failed_rooms']} failed; first: "
                         f"{first.get('tag')}: {first.get('error')})")


if __name__ == "__main__":
    main()
