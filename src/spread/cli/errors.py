"""User errors in one line, for every console script (docs/robustness.md).

* :func:`command` wraps a script's ``main`` (the Hydra app) and checks an ``out_dir=`` given on the command
  line *before* Hydra makes the run folder: an existing file, a read-only or unwritable folder is refused in
  one line (Hydra would stop with a traceback from deep inside itself); and, given the command's config name,
  composes the command line once first (:func:`compose_problem`): an override that names no key, does not parse
  or names no config group option, or a required setting (``???``) left unset, is refused in one line before
  Hydra prints its own message or a traceback from resolving the run folder.
* :func:`one_line` wraps the task function inside the Hydra app: a bad setting or input (``ValueError``,
  ``FileNotFoundError``, a refused file or folder — also when a constructor raised it inside Hydra's
  ``instantiate``) ends the command with ``<command>: <message>`` and exit status 1. ``HYDRA_FULL_ERROR=1`` (or
  ``SPREAD_DEBUG=1``) shows the full traceback instead.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

from spread.cli.user_errors import user_error, user_error_types, verbose  # noqa: F401 — this module's names too


def one_line(name: str):
    """Decorator of a Hydra task function: user errors become ``SystemExit("<name>: <message>")``."""

    def wrap(task):
        @functools.wraps(task)
        def run(*args, **kwargs):
            from spread.runtime.quiet import silence_known_noise

            silence_known_noise()
            try:
                return task(*args, **kwargs)
            except KeyboardInterrupt:  # Ctrl-C: one line, the shell's exit status for it (128 + SIGINT)
                if verbose():
                    raise
                print(f"{name}: interrupted (Ctrl-C)", file=sys.stderr, flush=True)
                raise SystemExit(130) from None
            except Exception as exc:  # noqa: BLE001 — only user errors are turned into one line
                cause = user_error(exc)
                if cause is None or verbose():
                    raise
                from spread.configs import error_message

                raise SystemExit(f"{name}: {error_message(cause)} (HYDRA_FULL_ERROR=1 shows the traceback)") from None

        return run

    return wrap


def ddp_child() -> bool:
    """Whether this process is a child Lightning's DDP launcher started (``LOCAL_RANK`` ≥ 1): it runs the command line
    again with ``hydra.run.dir=<the parent's run folder>`` added, so that every process writes into one folder."""
    return os.environ.get("LOCAL_RANK", "0") not in ("", "0")


def out_dir_problem(value: str) -> str | None:
    """Why ``out_dir=value`` cannot be a run folder (empty, an existing file, not writable, a link that loops or
    leads nowhere, a ``..`` after a link: :func:`link_then_up`), or None."""
    if not value.strip():  # the run went to the working folder, and Hydra's record of it to /logs/...
        return "out_dir= is empty; give a folder (out_dir=. for the working folder)"
    try:
        return link_then_up(value) or _out_dir_problem(value)
    except OSError as exc:  # a link that loops (ELOOP), a name too long, ...
        return f"out_dir={value}: not a usable path ({exc.strerror or type(exc).__name__}); give another out_dir"


def link_then_up(value: str) -> str | None:
    """Why ``out_dir=value`` with a ``..`` right after a symbolic link is refused, or None: the system goes up from
    where the link leads (``link/../b`` is ``b`` beside the link's target), but the temporary files of atomic writes
    and Hydra's run folder go by the text (``./b``), so the run's files would land in two folders."""
    from spread.io import normal_path

    text = Path(os.path.normpath(os.path.abspath(os.path.expanduser(value))))
    meant = normal_path(os.path.expanduser(value))
    if ".." not in Path(value).parts or meant == text:
        return None
    return (f"out_dir={value}: a '..' follows a symbolic link, so the system means {meant} while the text reads "
            f"{text}; give the folder without '..' (out_dir={meant})")


def _out_dir_problem(value: str) -> str | None:
    path = Path(value).expanduser()
    if path.exists() or path.is_symlink():
        if not path.is_dir():
            return f"out_dir={value}: exists and is not a folder; give a folder path"
        if not os.access(path, os.W_OK | os.X_OK):
            return f"out_dir={value}: the folder is not writable (read-only or another user's); give another out_dir"
        from spread.io import planted_link

        problem = planted_link(path)
        return f"out_dir={value}: {problem}" if problem else None
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        if parent.is_symlink():  # dangling (a loop raises ELOOP above)
            return f"out_dir={value}: {parent} is a symbolic link that leads nowhere ({os.readlink(parent)})"
        parent = parent.parent
    if not parent.is_dir():
        return f"out_dir={value}: {parent} is not a folder, so the run folder cannot be made there"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"out_dir={value}: cannot be created, {parent} is not writable (read-only file system or permissions)"
    return None


#: ``hydra/launcher=<name>`` (conf/hydra/launcher/) → the Hydra plugin module it needs and the package that has it
LAUNCHERS = {"parallel": ("hydra_plugins.hydra_joblib_launcher", "hydra-joblib-launcher"),
             "slurm": ("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher")}


def launcher_problem(value: str) -> str | None:
    """What is wrong with ``hydra/launcher=<value>`` here (its plugin is not installed), or None. Hydra itself says
    only "Could not load 'hydra/launcher/joblib'"."""
    import importlib.util

    if value not in LAUNCHERS:
        return None
    module, package = LAUNCHERS[value]
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        found = False
    if found:
        return None
    return (f"hydra/launcher={value} needs the Hydra launcher plugin {package}, which is not installed: "
            f"pip install -e '.[launchers]' (make demo / make test install it)")


def compose_problem(config: str, args: list[str], name: str = "") -> str | None:
    """What keeps the command line ``args`` from composing ``conf/<config>.yaml`` for one run, in one line, or None:
    an override that names no key, does not parse or convert, or names no config group option, or a required
    setting (``???``) that it leaves unset. A command line with Hydra's flags (``-m``, ``--cfg``, ``--help``, …) or
    a ``hydra.searchpath`` is left to Hydra; other ``hydra.*`` overrides are not part of the job's config. ``name``:
    the console script, named in the hint to print its settings."""
    return composed_ahead(config, args, name)[0]


def composed_ahead(config: str, args: list[str], name: str = ""):
    """(:func:`compose_problem`'s answer, the composed config or None where none was composed). A multirun
    (``-m``) is checked job by job (:func:`spread.cli.multirun.multirun_problem`); nothing composed is returned."""
    if any(a.lstrip("+~").startswith(("hydra.searchpath", "hydra.mode")) for a in args):  # other config sources
        return None, None
    from spread.cli.multirun import is_multirun, multirun_problem

    if is_multirun(args):
        return multirun_problem(config, args, name, composed_ahead), None
    if any(a.startswith("-") for a in args):  # Hydra's other flags (--cfg, --help, …)
        return None, None
    overrides = [a for a in args if not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from spread.configs import compose, error_message, required_message

    try:
        composed = compose(config, overrides)
    except (HydraException, OmegaConfBaseException) as exc:
        return error_message(exc), None
    try:
        missing = unset_keys(OmegaConf.to_container(composed, resolve=False, throw_on_missing=False))
    except Exception:  # noqa: BLE001 — the check never stands in Hydra's way: Hydra says what it finds
        return None, composed
    if not missing:
        return None, composed
    return required_message(missing, f"`{name} --cfg job` prints every setting" if name else ""), composed


def composed_value(composed, key: str):
    """``composed``'s ``key`` resolved, or None where it cannot be outside the running app (``${hydra:...}``)."""
    try:
        return composed.get(key)
    except Exception:  # noqa: BLE001 - an interpolation only the running app resolves
        return None


def unset_keys(plain, prefix: str = "") -> list[str]:
    """The dotted keys of a config (as plain data, interpolations unresolved: ``${hydra:...}`` or ``${point_dir:...}``
    resolve only inside the running app) whose value is OmegaConf's ``???``."""
    if isinstance(plain, dict):
        items = plain.items()
    elif isinstance(plain, list):
        items = enumerate(plain)
    else:
        return [prefix] if plain == "???" else []
    return [key for k, v in items for key in unset_keys(v, f"{prefix}.{k}" if prefix else str(k))]


def command(name: str, config: str | None = None):
    """Decorator of a console script's Hydra ``main``: refuse a bad ``out_dir=`` argument, or a Hydra launcher whose
    plugin is not installed (:func:`launcher_problem`), before Hydra runs; with ``config`` (the app's config name)
    also a command line that does not compose or leaves a required setting unset (:func:`compose_problem`)."""

    def wrap(main):
        @functools.wraps(main)
        def entry(*args, **kwargs):
            if args or kwargs:  # called with a composed config (``main(cfg)``), not from a command line
                try:
                    return main(*args, **kwargs)
                finally:
                    _RUN_FOLDERS.clear()  # the folders noted belong to this call, not to a later command's cleanup
            for arg in sys.argv[1:]:
                if arg.startswith("out_dir="):
                    problem = out_dir_problem(arg.split("=", 1)[1])
                    if problem:
                        raise SystemExit(f"{name}: {problem}")
                # the run went to hydra.run.dir while its record named out_dir's folder
                if arg.lstrip("+").startswith("hydra.run.dir=") and not ddp_child():
                    raise SystemExit(f"{name}: {arg.lstrip('+')}: Hydra's run folder follows out_dir (conf/hydra); "
                                     f"give out_dir=<folder> instead")
                if arg.lstrip("+").startswith("hydra/launcher="):
                    problem = launcher_problem(arg.split("=", 1)[1])
                    if problem:
                        raise SystemExit(f"{name}: {problem}")
            composed = None
            if config is not None:
                problem, composed = composed_ahead(config, sys.argv[1:], name)
                if problem:
                    raise SystemExit(f"{name}: {problem}")
                typed = any(a.startswith("out_dir=") for a in sys.argv[1:])  # checked above, as typed
                value = None if composed is None or typed else composed_value(composed, "out_dir")
                problem = out_dir_problem(value) if isinstance(value, str) else None
                if problem:  # ``++out_dir=``, a default, an interpolation
                    raise SystemExit(f"{name}: {problem}")
            left = FolderLeftEmpty.of(sys.argv[1:], composed)
            _RUN_FOLDERS.clear()
            try:
                return main(*args, **kwargs)
            except BaseException as exc:
                if not isinstance(exc, SystemExit) or exc.code not in (0, None):
                    left.remove()
                raise
            finally:
                _RUN_FOLDERS.clear()

        return entry

    return wrap


class FolderLeftEmpty:
    """A command's run folder, as it was before the command ran: a command that fails before it wrote anything
    (refused by its checks, after Hydra made the run folder and the run lock was taken) leaves behind no empty run
    folder, no empty folders it made in it (``scenes/``), none above it, no lock file it made (taken from it while
    held, :func:`spread.io.remove_held_lock`) and no record Hydra made of a run that did nothing (``logs/<command>/
    <time>/.hydra`` of a dataset command) (:meth:`remove`). The folder is the one the command ran in
    (:func:`note_run_folders`: ``out_dir`` as composed — a default, an interpolation, ``++out_dir=`` — and Hydra's
    run folder); whether it and the folders above it were there before comes from the command line composed ahead
    (``planned``), and the folders creating it as written made on the way (``a`` of ``out_dir=a/../b``:
    :func:`on_the_way`). A folder that was there stays (only what the command made in it goes); anything else in it
    stays."""

    def __init__(self, planned: Path | None, written: str | None = None):
        self.planned = planned
        self.existed: dict[Path, bool] = {}  # the planned folder and those above it: there before the command?
        if planned is not None:
            for path in (planned, *planned.parents):
                self.existed[path] = os.path.lexists(path)
        self.on_the_way = on_the_way(written) if written else []

    @classmethod
    def of(cls, args: list[str], composed=None) -> "FolderLeftEmpty":
        """From the command line ``args`` and, when given, its config composed ahead (its ``out_dir`` resolved where
        it can be outside the app); a multirun's jobs write their own folders: nothing to keep."""
        if any(a in ("-m", "--multirun") or a.lstrip("+").startswith("hydra.mode") for a in args):
            return cls(None)
        value = None if composed is None else composed_value(composed, "out_dir")
        if value is None:
            given = [a.split("=", 1)[1] for a in args if a.lstrip("+").startswith("out_dir=")]
            value = given[-1] if given else None
        from spread.io import normal_path

        if not (isinstance(value, str) and value):
            return cls(None)
        return cls(normal_path(value), value)

    def remove(self) -> None:
        from spread.io import LOCK_FILE, made_lock, remove_held_lock

        folder = _RUN_FOLDERS.get("out_dir") or self.planned
        if folder is None:
            return
        fresh = not self.existed.get(folder, False)  # not planned: a folder named at run time (a time stamp): new
        try:
            hydra = _RUN_FOLDERS.get("hydra")
            if hydra is not None and folder in hydra.parents:
                remove_hydra_record(hydra, folder)
            if fresh:
                remove_empty_folders(folder)
            lock = folder / LOCK_FILE
            if made_lock(lock):
                remove_held_lock(lock)
            if fresh:
                folder.rmdir()  # only when empty
                for path in folder.parents:
                    if self.existed.get(path, True):
                        break
                    path.rmdir()  # a folder made on the way; one with anything in it ends the walk
        except OSError:
            pass
        for path in reversed(self.on_the_way):  # ``a`` of ``out_dir=a/../b``: made by creating the path as written
            try:
                path.rmdir()  # only when empty
            except OSError:
                pass


def on_the_way(written: str) -> list[Path]:
    """The folders that creating ``written`` as written (``os.makedirs``, ``Path.mkdir(parents=True)``) makes and
    that are not there now, outermost first, normalised: ``a`` of ``a/../b`` (the normalised path names only ``b``);
    none for a path without ``..``."""
    from spread.io import normal_path

    path = Path(written if os.path.isabs(written) else os.path.join(os.getcwd(), written))
    if ".." not in path.parts:
        return []
    prefixes = [Path(*path.parts[:i]) for i in range(2, len(path.parts) + 1)]
    made = [normal_path(p) for p in prefixes if p.name not in ("..", ".")]
    return [p for p in dict.fromkeys(made) if not os.path.lexists(p)]


def remove_empty_folders(folder: Path) -> None:
    """Remove the empty folders inside ``folder`` (a run folder this command made), deepest first; links are not
    followed and nothing else is touched."""
    for root, dirs, _files in os.walk(folder, topdown=False):
        for name in dirs:
            path = Path(root) / name
            if not path.is_symlink():
                try:
                    path.rmdir()
                except OSError:
                    pass


#: Hydra's record of a run (``output_subdir: .hydra``): with empty logs, all a command refused at once leaves there.
HYDRA_RECORD = {".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml"}


def remove_hydra_record(hydra: Path, folder: Path) -> None:
    """Remove Hydra's run folder ``hydra`` (inside ``folder``) when it holds only Hydra's record of this run and
    empty logs, then the empty folders between it and ``folder``."""
    files = [Path(root) / f for root, _dirs, names in os.walk(hydra) for f in names]
    if any(f.is_symlink() or not (f.relative_to(hydra).as_posix() in HYDRA_RECORD or
                                  (f.suffix == ".log" and f.stat().st_size == 0)) for f in files):
        return
    for f in files:
        f.unlink()
    remove_empty_folders(hydra)
    hydra.rmdir()
    for path in hydra.parents:
        if path == folder:
            break
        path.rmdir()


#: The folders the running command's app was given (:func:`note_run_folders`): ``out_dir`` and ``hydra``.
_RUN_FOLDERS: dict[str, Path] = {}


def note_run_folders(cfg) -> None:
    """Note the run folders of the command now running (its composed ``out_dir``, Hydra's run folder) for
    :class:`FolderLeftEmpty`; a config without them notes nothing."""
    try:
        from hydra.core.hydra_config import HydraConfig

        from spread.io import normal_path

        out_dir = cfg.get("out_dir")
        if isinstance(out_dir, str) and out_dir:
            _RUN_FOLDERS["out_dir"] = normal_path(out_dir)
        _RUN_FOLDERS["hydra"] = normal_path(HydraConfig.get().runtime.output_dir)
    except Exception:  # noqa: BLE001 - nothing to note: nothing is removed on its account
        pass


def console_main(name: str, config: str):
    """Decorator of a Hydra console script's task function: the app's config ``config`` named once, for the
    pre-composed check of its command line (:func:`command`), for ``hydra.main`` and for the structured-config
    schemas it composes with (:func:`spread.configs.register`); user errors in one line (:func:`one_line`)."""
    import hydra

    from spread.configs import conf_dir, register

    register(config)

    def wrap(task):
        @functools.wraps(task)
        def noted(cfg):
            note_run_folders(cfg)
            return task(cfg)

        hydra_main = hydra.main(config_path=conf_dir(), config_name=config, version_base="1.3")(one_line(name)(noted))
        return command(name, config=config)(hydra_main)

    return wrap
