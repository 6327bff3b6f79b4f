"""A normal (non-editable) install runs: the wheel carries the config tree and the segmentation zoo (the detection
zoo's wheel its detectors; each within 100 MB), and the installed package composes, builds models and runs the smoke
experiment from a directory that is not the checkout. Also the Hydra surface a user sees: the job's name and the
launcher presets."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

from omegaconf import OmegaConf
import pytest

from pairedgta.configs import CONFIG_DIR
from pairedgta.testing.cli import OFFLINE, compose_cfg, run_cli

CHECKOUT = Path(__file__).resolve().parents[1]
# the names the launcher plugins register in Hydra's ConfigStore (a YAML of the same name shadows the schema)
PLUGIN_LAUNCHERS = {"basic", "joblib", "submitit_local", "submitit_slurm"}


# the project's distributions: the package, and the detection zoo's weights apart (zoo/detection/pyproject.toml)
DISTRIBUTIONS = {"pairedgta": CHECKOUT, "pairedgta_detection_zoo": CHECKOUT / "zoo" / "detection"}
WHEEL_LIMIT = 100 * 10**6  # a package index's default file limit (PyPI: 100 MB), in the stricter decimal reading


def _build_wheels(tmp: Path) -> dict[str, Path]:
    """Every distribution's wheel, built from copies of the sources (so the checkout gets no build/ or egg-info)
    in one pip call."""
    sources = []
    for dist_name, project in DISTRIBUTIONS.items():
        src = tmp / f"src_{dist_name}"
        src.mkdir()
        for name in ("pyproject.toml", "README.md"):
            if (project / name).is_file():
                shutil.copy2(project / name, src / name)
        for package in _top_packages(project):
            shutil.copytree(project / package, src / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        sources.append(str(src))
    dist = tmp / "dist"
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                           str(dist), *sources], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    wheels = {}
    for dist_name in DISTRIBUTIONS:
        (wheels[dist_name],) = dist.glob(f"{dist_name}-*.whl")
    return wheels


def _setuptools_conf(project: Path) -> dict:
    import tomllib

    return tomllib.loads((project / "pyproject.toml").read_text())["tool"]["setuptools"]


def _top_packages(project: Path) -> list[str]:
    conf = _setuptools_conf(project)
    names = conf["packages"] if isinstance(conf.get("packages"), list) else conf["packages"]["find"]["include"]
    return sorted({n.rstrip("*").split(".")[0] for n in names})


def _shipped_bytes(project: Path) -> int:
    """What the project's wheel holds, uncompressed: its modules and the files its package-data globs match (the
    weights dominate and barely compress, so this bounds the wheel's size from above, give or take the zip's index)."""
    files = {p for package in _top_packages(project) for p in (project / package).rglob("*.py")}
    for package, patterns in _setuptools_conf(project).get("package-data", {}).items():
        root = project / package.replace(".", "/")
        files |= {p for pattern in patterns for p in root.glob(pattern) if p.is_file()}
    return sum(p.stat().st_size for p in files)


def test_every_wheel_the_project_builds_stays_within_a_package_index_s_limit():
    """Both zoos in one wheel passed 100 MB: the detectors ship in a distribution of their own. Each wheel's content
    is summed from its pyproject's package data (fast, offline); the slow test below builds both and checks them."""
    sizes = {name: _shipped_bytes(project) for name, project in DISTRIBUTIONS.items()}
    assert all(sizes.values()) and sizes["pairedgta_detection_zoo"] > 10 * 10**6, sizes  # the globs match the weights
    for name, size in sizes.items():
        assert size <= WHEEL_LIMIT - 2 * 10**6, f"{name}'s wheel would hold {size / 1e6:.1f} MB (limit 100 MB): move " \
                                                 "weights into another distribution (zoo/)"
    # the package requires its companion at the companion's version (README's install line installs both)
    import tomllib

    deps = tomllib.loads((CHECKOUT / "pyproject.toml").read_text())["project"]["dependencies"]
    zoo = tomllib.loads((DISTRIBUTIONS["pairedgta_detection_zoo"] / "pyproject.toml").read_text())["project"]
    assert f"{zoo['name']}=={zoo['version']}" in deps


def _venv_seeing_these_packages(env_dir: Path) -> Path:
    """A venv whose dependencies are the running interpreter's. `system_site_packages=True` would give the
    *base* interpreter's, which inside a venv (README's install in `python -m venv`) lack them all; a .pth
    naming this interpreter's site directories works in both cases. Only those directories are added,
    not their .pth files, so the checkout's editable install of pairedgta stays out of sight."""
    import site
    import sysconfig

    venv.EnvBuilder(system_site_packages=False, with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    dirs = [d for d in [*site.getsitepackages(), sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]]
            if Path(d).is_dir()]
    target = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                            capture_output=True, text=True, check=True).stdout.strip()
    (Path(target) / "zz_parent_site_packages.pth").write_text("\n".join(dict.fromkeys(dirs)) + "\n")
    return py


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    wheels = _build_wheels(tmp_path)
    wheel, zoo_wheel = wheels["pairedgta"], wheels["pairedgta_detection_zoo"]
    for built in (wheel, zoo_wheel):
        assert built.stat().st_size <= WHEEL_LIMIT, f"{built.name}: {built.stat().st_size / 1e6:.1f} MB"
    names = set(zipfile.ZipFile(wheel).namelist())
    zoo_names = set(zipfile.ZipFile(zoo_wheel).namelist())
    assert "pairedgta_detection_zoo/demo_det_reference/model.safetensors" in zoo_names
    assert not any(n.startswith("pairedgta/models/weights/demo_det_reference/") for n in names)
    shipped_yaml = {f"pairedgta/conf/{p.relative_to(CONFIG_DIR).as_posix()}" for p in CONFIG_DIR.rglob("*.yaml")}
    assert shipped_yaml and shipped_yaml <= names, sorted(shipped_yaml - names)
    weights = CONFIG_DIR.parent / "models" / "weights" / "demo_segformer"
    assert {f"pairedgta/models/weights/demo_segformer/{p.name}" for p in weights.iterdir()} <= names

    # a fresh environment: the running interpreter's site-packages give the dependencies (no downloads),
    # the wheel gives pairedgta; the checkout is neither the working directory nor on sys.path
    env_dir = tmp_path / "venv"
    py = _venv_seeing_these_packages(env_dir)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(OFFLINE, PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PYTHONWARNINGS="ignore")
    proc = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "-q", str(wheel), str(zoo_wheel)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    work = tmp_path / "elsewhere"
    work.mkdir()

    # (building a model is left to the run below, which builds the smoke experiment's two)
    probe = ("import pairedgta, sys; from pairedgta.models import available_models; from pathlib import Path; "
             "print(pairedgta.__file__); print(any(p and Path(p).resolve() == Path(sys.argv[1]).resolve() for p in sys.path)); "
             "print(','.join(available_models())); from pairedgta.models.hf_common import resolve_checkpoint_path; "
             "print(resolve_checkpoint_path('pkg://models/weights/demo_det_reference/model.safetensors'))")
    proc = subprocess.run([str(py), "-c", probe, str(CHECKOUT)], cwd=work, capture_output=True, text=True, env=env,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    where, checkout_on_path, models, detector = proc.stdout.strip().splitlines()[-4:]
    assert Path(where).resolve().is_relative_to(env_dir.resolve()), where  # the wheel's copy, not the checkout
    # the detectors' weights from the companion's wheel, under the model configs' unchanged pkg:// paths
    assert Path(detector).is_file() and Path(detector).resolve().is_relative_to(env_dir.resolve()), detector
    assert checkout_on_path == "False"  # (a venv made inside the checkout, e.g. .venv/, is fine)
    assert "tiny_segformer" in models.split(",") and "demo_segformer" in models.split(",")

    run_dir = tmp_path / "run"
    cache = tmp_path / "cache"
    proc = subprocess.run(
        [str(py), "-m", "pairedgta", "+experiment=smoke", "tracking.enabled=false", f"cache_dir={cache}",
         "renderer.width=48", "renderer.height=32", "generate.num_scenes=2", "metric.bootstrap.resamples=20",
         "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]", "plot.formats=[png]", "plot.dpi=40",
         "plot.figures=[xi_table]", f"hydra.run.dir={run_dir}"],
        cwd=work, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"results: {cache / 'plot'}" in proc.stdout
    plots = [p for p in (cache / "plot").iterdir() if not p.name.startswith(".")]
    assert len(plots) == 1 and any(f.name.startswith("xi_") and f.suffix == ".png" for f in plots[0].iterdir())
    # Hydra's job is named pairedgta (not __main__), and its log file ends with where the results are
    log_text = (run_dir / "pairedgta.log").read_text()
    assert f"results: {plots[0]}" in log_text
    assert not (work / "mlruns").exists()


@pytest.mark.slow
def test_help_names_the_app(tmp_path):
    proc = run_cli(["--help"], tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert out.startswith("pairedgta: perfectly paired driving images") and "__main__" not in out
    for experiment in ("smoke", "metric_validity", "paper_table", "night_vs_acdc", "cost_analysis"):
        assert f"+experiment={experiment}" in out  # the experiments, each with its command
    assert "model: " in out and "demo_ddrnet" in out and "renderer: " in out  # Hydra's list of group options
    assert "CUEW" not in proc.stdout + proc.stderr  # Blender's CUDA probe stays quiet on a CPU machine


def test_launcher_presets_extend_the_plugins_instead_of_shadowing_them():
    """A YAML named like a plugin's schema (joblib, submitit_slurm) makes Hydra warn on every job of a
    sweep; the project's presets have their own names and start from the plugin's config."""
    presets = sorted((CONFIG_DIR / "hydra" / "launcher").glob("*.yaml"))
    assert presets
    for path in presets:
        assert path.stem not in PLUGIN_LAUNCHERS, path
        defaults = OmegaConf.load(path).get("defaults")
        assert defaults and defaults[0] in PLUGIN_LAUNCHERS and defaults[-1] == "_self_", path
    # and the run's own config composes without any launcher plugin installed
    assert compose_cfg([]).name == "default"
