"""`python -m pairedgta +experiment=<name>`: compose the config, run the stage graph, log to MLflow."""
from __future__ import annotations

import logging
import os
import signal
import sys

if __name__ == "__main__":  # `python -m pairedgta`: the tracking child's MLflow imports start before Hydra's
    from pairedgta.tracking import background as _tracking_child

    _tracking_child.prestart(sys.argv[1:])

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from hydra.errors import CompactHydraException  # noqa: E402

from pairedgta.errors import PairedGTAError, Terminated, write_failed  # noqa: E402

log = logging.getLogger("pairedgta")

# run folders carry the pid: two runs started in the same second never share one
if not OmegaConf.has_resolver("pid"):
    OmegaConf.register_new_resolver("pid", lambda: os.getpid(), use_cache=True)


class JobError(CompactHydraException):
    """A sweep job's one-line error, carried back by the launcher: Hydra prints a compact error as its
    message alone, so the sweep's output shows the job's error where a traceback would be."""


def _terminate(signum: int, frame: object) -> None:
    from pairedgta import interrupt

    if not interrupt.request(signum):  # else raised by interrupt.check() once Cycles has returned
        raise Terminated(f"stopped by {signal.Signals(signum).name}")


def _interrupt(signum: int, frame: object) -> None:
    from pairedgta import interrupt

    if not interrupt.request(signum):
        raise KeyboardInterrupt


@hydra.main(version_base="1.3", config_path="pkg://pairedgta.conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from pairedgta.app import run
    from pairedgta.cache import StageCache, release_all

    # PDF font subsetting logs every table at INFO; keep the run log about the run
    logging.getLogger("fontTools").setLevel(logging.WARNING)
    # SIGTERM (kill, a scheduler's cancel) unwinds like Ctrl-C: temp folders go, MLflow marks KILLED
    previous = signal.signal(signal.SIGTERM, _terminate) if _main_thread() else None
    previous_int = signal.signal(signal.SIGINT, _interrupt) if _main_thread() else None

    from hydra.core.hydra_config import HydraConfig

    from pairedgta import launchers

    launchers.quiet_job_log()
    try:
        from pairedgta.config_checks import check_added_keys

        check_added_keys(list(HydraConfig.get().overrides.task), dict(HydraConfig.get().runtime.choices))
        summary = run(cfg, task_overrides=list(HydraConfig.get().overrides.task))
    except PairedGTAError as exc:
        # one line, no traceback: the message names the file/key and the fix
        _close_progress_bars()
        print(f"error: {exc}", file=sys.stderr)
        _to_log_files([f"error: {exc}"], logging.ERROR)
        if _in_sweep():  # the launcher carries it back to the sweep, which prints it as one line
            raise JobError(_job_line(exc)) from None
        sys.exit(2)
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"error: interrupted ({str(exc) or 'Ctrl-C'}); finished work is kept, rerun to resume", file=sys.stderr)
        sys.exit(130 if isinstance(exc, KeyboardInterrupt) else 143)
    except OSError as exc:  # a full disk (a failed write) outside a cache entry's build (which says so itself)
        full = write_failed(exc, os.path.dirname(str(exc.filename)) if exc.filename else cfg.get("cache_dir"))
        if full is None:
            raise
        _close_progress_bars()
        print(f"error: {full}", file=sys.stderr)
        _to_log_files([f"error: {full}"], logging.ERROR)
        sys.exit(2)
    finally:
        release_all()
        from pairedgta import interrupt

        interrupt.clear()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if previous_int is not None:
            signal.signal(signal.SIGINT, previous_int)
    # a successful run also clears resumable work crashed runs left and nobody resumed
    StageCache(str(cfg.cache_dir)).sweep(partials=True)
    where = (summary.get("plot") or next(iter(summary.get("evaluate", {}).values()), None) or summary.get("dataset")
             or summary.get("generate"))
    lines = [f"results: {where}"] + [f"  evaluate [{name}]: {path}" for name, path in summary.get("evaluate", {}).items()]
    if summary.get("mlflow"):
        lines.append(f"  mlflow: {summary['mlflow']}")
    from pairedgta.report import unpredictable_lines, xi_lines

    lines += [f"  {line}" for line in xi_lines(summary.get("evaluate", {}),
                                               OmegaConf.select(cfg, "conditions.reference", default=None))]
    lines += [f"  {line}" for line in unpredictable_lines(summary.get("evaluate", {}))]
    if OmegaConf.select(cfg, "conditions.corruptions", default=None) and summary.get("evaluate"):
        from pathlib import Path

        from pairedgta.corruption_summary import terminal_summary  # Cityscapes-C / Michaelis: P, mPC, rPC

        text = terminal_summary([Path(p) for p in summary["evaluate"].values()],
                                str(OmegaConf.select(cfg, "conditions.reference", default="")))
        lines += [f"  {line}" for line in text.splitlines()]
    print("\n".join(lines))
    _to_log_files(lines)


def _close_progress_bars() -> None:
    """A stage's progress bar that an error left open ends its line first: the error is a line of its own
    (a bar over an iterator an exception left is closed only when it is collected)."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ()) or ()):
        try:
            bar.close()
        except Exception:  # pragma: no cover - a bar half torn down: the error line matters more
            pass


def _to_log_files(lines: list[str], level: int = logging.INFO) -> None:
    """The `results:` lines go to stdout bare (to copy a path) and the one-line error to stderr; both also go
    into the job's log file(s), so the log of a run says where its results are or why it stopped: logging
    them would print them twice on the console."""
    handlers = [h for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]
    for line in lines:
        record = log.makeRecord(log.name, level, __file__, 0, line, None, None)
        for h in handlers:
            h.handle(record)


def _in_sweep() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


def _job_line(exc: BaseException) -> str:
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    overrides = " ".join(hc.overrides.task)
    return f"error: job #{hc.job.num} ({overrides}): {exc} (log: {hc.runtime.output_dir}/{hc.job.name}.log)"


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


OPEN_MAPPINGS = ("model_overrides.", "camera.overrides.", "model.kwargs.")  # model.kwargs: a model=python factory's arguments


def _open_mapping_overrides(argv: list[str]) -> list[str]:
    """`model_overrides.<name>.<key>=v` and `camera.overrides.<condition>=ev` add keys to mappings that are empty in
    the config files, which Hydra's struct mode refuses without a `+`; they are open by design, so their keys go in
    as `++` (and are checked by the code that reads them). So do
    `model.<key>=v` for a key some family reads (model.amp, model.batch_size): a model YAML names only what
    differs from the defaults (pairedgta/models/runtime.py), and the family's check names a key it does not read."""
    model_keys: set[str] | None = None
    out = []
    for a in argv:
        if a.startswith("model.") and "=" in a:
            if model_keys is None:
                from pairedgta.models import model_keys as keys_of_families

                model_keys = keys_of_families()
            if a.split("=", 1)[0][len("model."):] in model_keys:
                a = f"++{a}"
        out.append(f"++{a}" if a.startswith(OPEN_MAPPINGS) and "=" in a else a)
    return out


# keys that moved in a release: the old name says where to
MOVED_KEYS = {"renderer.exposure_bias": "camera.bias", "renderer.exposure": "camera.overrides",
              "renderer.view_transform": "camera.view_transform", "renderer.look": "camera.look"}


def mistyped_key(argv: list[str]) -> str | None:
    """A `key=value` whose key the composed config will not have gets Hydra's five-line "not in struct" message
    and the advice to prepend `+`, which the tool then refuses: one line naming the key and its group option
    (the chosen one: renderer=synthetic has other keys than blender) or the closest known key instead."""
    import difflib

    from pairedgta.config_checks import (BUILT_NODES, argv_choices, check_group_key, check_package_key,
                                         known_key_paths, open_key)
    from pairedgta.errors import ConfigError

    known: set[str] | None = None
    choices: dict[str, str] | None = None
    for arg in argv:
        if arg.startswith(("-", "+", "~")) or "=" not in arg:
            continue
        key = arg.split("=", 1)[0].strip()
        if "/" in key or open_key(key):
            continue
        moved = next((old for old in MOVED_KEYS if key == old or key.startswith(old + ".")), None)
        if moved:
            return f"{moved} is now {MOVED_KEYS[moved]} (the camera group, pairedgta/conf/camera/); set that instead"
        choices = choices if choices is not None else argv_choices(argv)
        try:  # a node an experiment's defaults add (`/dataset@acdc: acdc`): the keys of that option
            if check_package_key(key, choices):
                continue
        except ConfigError as exc:
            return str(exc)
        if key.split(".")[0] in choices and "." in key:
            try:  # the same check as a `+group.key`, against the option this command line chooses
                check_group_key(key, choices)
            except ConfigError as exc:
                return str(exc)
        known = known if known is not None else known_key_paths()
        if key in known or (key.split(".")[0] in BUILT_NODES and key.count(".") > 1):
            continue  # a key inside a built node's mapping (e.g. renderer.town.x) is checked by its builder
        close = difflib.get_close_matches(key, sorted(k for k in known if not key.startswith(k + ".")), n=1, cutoff=0.8)
        parent = key.rpartition(".")[0]
        siblings = sorted(k.rpartition(".")[2] for k in known if k.rpartition(".")[0] == parent)
        hint = (f"did you mean {close[0]}?" if close else
                f"{f'the keys of {parent} are' if parent else 'its top-level keys are'} {', '.join(siblings)}"
                if siblings else "see python -m pairedgta --cfg job for the keys")
        return f"{key} is not a key of pairedgta; {hint}"
    return None


def cli() -> None:
    from pairedgta.tracking import background

    sys.argv[1:] = _open_mapping_overrides(sys.argv[1:])
    wrong = mistyped_key(sys.argv[1:])
    if wrong:
        print(f"error: {wrong}", file=sys.stderr)
        sys.exit(2)
    if {"-m", "--multirun"} & set(sys.argv[1:]):
        from pairedgta import launchers

        launchers.install()  # SLURM job states from squeue where accounting is off
    background.prestart(sys.argv[1:])
    try:
        main()
    finally:
        background.discard()


if __name__ == "__main__":
    cli()
