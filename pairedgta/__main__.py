"""`python -m pairedgta +experiment=<name>`: compose the config, run the stage graph, log to MLflow."""
from __future__ import annotations

import logging
import sys

import hydra
from omegaconf import DictConfig

from pairedgta.errors import PairedGTAError

log = logging.getLogger("pairedgta")


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from pairedgta.app import run

    # PDF font subsetting logs every table at INFO; keep the run log about the run
    logging.getLogger("fontTools").setLevel(logging.WARNING)

    from hydra.core.hydra_config import HydraConfig

    try:
        summary = run(cfg, task_overrides=list(HydraConfig.get().overrides.task))
    except PairedGTAError as exc:
        # one line, no traceback: the message names the file/key and the fix
        print(f"error: {exc}", file=sys.stderr)
        log.error("%s", exc)
        sys.exit(2)
    where = (summary.get("plot") or next(iter(summary.get("evaluate", {}).values()), None) or summary.get("dataset")
             or summary.get("generate"))
    print(f"results: {where}")
    for name, path in summary.get("evaluate", {}).items():
        print(f"  evaluate [{name}]: {path}")


OPEN_MAPPINGS = ("model_overrides.",)


def _open_mapping_overrides(argv: list[str]) -> list[str]:
    """`model_overrides.<name>.<key>=v` adds keys to a mapping that is empty in conf/config.yaml, which
    Hydra's struct mode refuses without a `+`; that mapping is open by design, so its keys go in as `++`."""
    return [f"++{a}" if a.startswith(OPEN_MAPPINGS) and "=" in a else a for a in argv]


def cli() -> None:
    sys.argv[1:] = _open_mapping_overrides(sys.argv[1:])
    main()


if __name__ == "__main__":
    cli()
