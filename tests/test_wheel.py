"""The package as users install it: the sdist and the wheel built from a copy of the tree, the
wheel installed with its dependencies into a bare virtual environment, and the console script run
from an empty folder.

The virtual environment is created WITHOUT ``--system-site-packages``: the test interpreter's
site-packages hold the editable install (a path finder that serves any package from the
checkout, listed in the wheel or not) and, in a user's venv, nothing of the base interpreter is
needed. pip installs the wheel with the extras it names and resolves its declared dependencies
itself, torch pinned to the running version (the local wheel the README's install command and CI
use).

Speed: resolving the ~35 dependencies against the package indexes (PyPI's pages of torch and
numpy are megabytes) took 60-90 s, more than unpacking them (measured on a loaded 2-core
machine). The dependencies are therefore resolved and downloaded once per set of
declared requirements (:func:`wheelhouse`: a folder under the user's cache, keyed by the
wheel's ``Requires-Dist``, the extras, the torch pin and the platform), and each run installs
from it with ``--no-index``: still pip's own resolution of the wheel's metadata into a bare
venv, so a dependency the wheel forgets to declare is still missing there, and a changed
requirement makes a new key (a new download). ``.pyc`` files are not compiled
(``--no-compile``: byte-compiling torch's thousands of modules tripled the unpacking time, and
changes nothing the test checks).

One module-scoped fixture builds and installs once; the tests share it.
"""

from __future__ import annotations

import email
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

import pytest

import torchcontact

ROOT = Path(__file__).resolve().parents[1]
#: Source folders -> the package each one is installed as (pyproject.toml's package-dir).
PACKAGE_ROOTS = {
    "torchcontact": "torchcontact",
    "training": "torchcontact.apps.training",
    "export": "torchcontact.apps.export",
}
#: Data files each installed package must carry (pyproject.toml's package-data), as globs.
PACKAGE_DATA = {"torchcontact": ["data/**/*"], "training": ["configs/*.toml"]}
EXTRAS = "logs,export,train"

TINY_CONFIG = """
[data]
frames = 1200
block_seconds = 1.0
folds = 0
[model]
kind = "mlp"
hidden = 8
layers = 1
[train]
epochs = 2
"""


def run_child(cmd: list[str], *, cwd: Path | None = None, env=None, timeout: float = 300) -> str:
    """Run a child process; on failure the assertion shows its command, exit code and stderr."""
    res = subprocess.run(
        [str(c) for c in cmd], capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout
    )
    if res.returncode != 0:
        pytest.fail(
            f"{' '.join(map(str, cmd))} (in {cwd}) exited with {res.returncode}\n"
            f"--- stderr ---\n{res.stderr[-4000:]}\n--- stdout ---\n{res.stdout[-2000:]}",
            pytrace=False,
        )
    return res.stdout


def _ignore(folder: str, names: list[str]) -> set[str]:
    """What a copy of the tree leaves out: VCS, caches, build outputs, logs and virtual
    environments (the README's ``python3 -m venv v`` may live inside the checkout)."""
    skip = set()
    for n in names:
        p = Path(folder) / n
        if (
            n.startswith(".")
            or n in ("build", "dist", "__pycache__", "out")
            or n.endswith((".egg-info", ".parquet", ".onnx"))
            or (p.is_dir() and (p / "pyvenv.cfg").exists())
        ):
            skip.add(n)
    return skip


def source_packages(root: Path = ROOT) -> dict[str, Path]:
    """Installed name -> folder of every package (a folder with ``__init__.py``) of the tree."""
    out = {}
    for folder, installed in PACKAGE_ROOTS.items():
        base = root / folder
        for init in sorted(base.rglob("__init__.py")):
            rel = init.parent.relative_to(base)
            if any(part.startswith((".", "__")) for part in rel.parts):
                continue
            out[".".join([installed, *rel.parts])] = init.parent
    return out


def source_data(root: Path = ROOT) -> set[str]:
    """Wheel paths of the data files of the tree (``torchcontact/data/...``, the configs)."""
    out = set()
    for folder, patterns in PACKAGE_DATA.items():
        prefix = PACKAGE_ROOTS[folder].replace(".", "/")
        for pattern in patterns:
            for f in (root / folder).glob(pattern):
                if f.is_file() and "__pycache__" not in f.parts:
                    out.add(f"{prefix}/{f.relative_to(root / folder).as_posix()}")
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, Path]:
    """sdist and wheel of a copy of the tree; the wheel is built from the sdist (``build``)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=_ignore)
    dist = tmp / "dist"
    # sdist first, then the wheel from the unpacked sdist: a file the sdist forgets is missing
    # from the wheel too. No build isolation: the build backend (setuptools) of this environment
    # (test extra) builds, so no second download of setuptools per run.
    run_child([sys.executable, "-m", "build", "--no-isolation", "--outdir", dist, src], cwd=tmp)
    (wheel,) = dist.glob("torchcontact-*.whl")
    (sdist,) = dist.glob("torchcontact-*.tar.gz")
    return {"wheel": wheel, "sdist": sdist, "src": src, "tmp": tmp}


def test_wheel_and_sdist_hold_every_package_and_data_file(built):
    names = set(zipfile.ZipFile(built["wheel"]).namelist())
    packages = source_packages(built["src"])
    assert {"torchcontact.estimation", "torchcontact.kernels", "torchcontact.apps.training"} <= set(
        packages
    )
    missing = [p for p in packages if f"{p.replace('.', '/')}/__init__.py" not in names]
    assert not missing, f"packages of the tree missing from {built['wheel'].name}: {missing}"
    # every module of every package, not only the __init__.py
    modules = {
        f"{p.replace('.', '/')}/{f.name}" for p, d in packages.items() for f in d.glob("*.py")
    }
    assert not sorted(modules - names), sorted(modules - names)
    data = source_data(built["src"])
    assert "torchcontact/data/robots/tcarm.urdf" in data
    assert "torchcontact/apps/training/configs/example.toml" in data
    assert not sorted(data - names), f"data files missing from the wheel: {sorted(data - names)}"
    # the applications are installed in the torchcontact namespace, not as top-level names
    tops = {n.split("/")[0] for n in names}
    assert tops == {"torchcontact", f"torchcontact-{torchcontact.__version__}.dist-info"}, tops
    meta = email.message_from_bytes(
        zipfile.ZipFile(built["wheel"]).read(
            f"torchcontact-{torchcontact.__version__}.dist-info/METADATA"
        )
    )
    assert meta["Version"] == torchcontact.__version__
    # the sdist holds the sources the wheel was built from, and the tests
    with tarfile.open(built["sdist"]) as tar:
        members = {m.split("/", 1)[1] for m in tar.getnames() if "/" in m}
    for folder in PACKAGE_ROOTS:
        for f in (built["src"] / folder).rglob("*.py"):
            if "__pycache__" not in f.parts:
                assert f.relative_to(built["src"]).as_posix() in members, f
    assert "pyproject.toml" in members and "README.md" in members


def _clean_env() -> dict[str, str]:
    """The environment of the children: no path or venv of the test interpreter leaks in."""
    drop = ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")
    return {k: v for k, v in os.environ.items() if k not in drop}


def wheelhouse(wheel: Path, extras: str, pins: list[str]) -> Path:
    """Wheels of everything ``wheel[extras]`` needs, downloaded once per set of requirements.

    The key hashes the wheel's ``Requires-Dist``, the extras, the pins, the Python version and
    the platform. Downloaded into a temporary folder beside the target and renamed into place
    under a file lock, so a concurrent or killed run never leaves a partial wheelhouse; the
    wheelhouses of other keys (stale requirements) are removed.
    ``TORCHCONTACT_TEST_WHEELHOUSE`` relocates the cache (default: ``~/.cache/torchcontact-tests``).
    """
    import hashlib
    import platform
    import sysconfig

    from filelock import FileLock

    with zipfile.ZipFile(wheel) as z:
        meta_name = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        requires = email.message_from_bytes(z.read(meta_name)).get_all("Requires-Dist") or []
    key = hashlib.sha256(
        json.dumps(
            [sorted(requires), extras, pins, platform.python_version_tuple()[:2],
             sysconfig.get_platform()]
        ).encode()
    ).hexdigest()[:16]  # fmt: skip
    root = Path(
        os.environ.get("TORCHCONTACT_TEST_WHEELHOUSE")
        or Path.home() / ".cache" / "torchcontact-tests"
    )
    root.mkdir(parents=True, exist_ok=True)
    target = root / f"wheelhouse-{key}"
    with FileLock(str(root / f"wheelhouse-{key}.lock")):
        if not target.is_dir():
            partial = Path(tempfile.mkdtemp(prefix=f"wheelhouse-{key}.", dir=root))
            try:
                # resolved against the package indexes, as pip install does; the project
                # itself is not kept (each run installs the freshly built wheel)
                run_child(
                    [sys.executable, "-m", "pip", "download", "--quiet", "--dest", partial,
                     *pins, f"{wheel}[{extras}]"],
                    env=_clean_env(), timeout=900,
                )  # fmt: skip
                for own in partial.glob("torchcontact-*"):
                    own.unlink()
                os.replace(partial, target)
            finally:
                shutil.rmtree(partial, ignore_errors=True)
    for old in root.glob("wheelhouse-*"):  # other requirement sets: stale, 300+ MB each
        if old.is_dir() and old != target and "." not in old.name:  # not another's partial
            try:
                with FileLock(str(old) + ".lock", timeout=0):  # not in use by another run
                    shutil.rmtree(old, ignore_errors=True)
            except TimeoutError:
                pass
    return target


@pytest.fixture(scope="module")
def installed(built) -> dict[str, Path]:
    """A bare venv with the wheel and its dependencies; an empty working folder."""
    tmp, env = built["tmp"], _clean_env()
    venv = tmp / "venv"
    # no --system-site-packages; no pip inside either (ensurepip costs seconds): this
    # interpreter's pip installs into it (pip --python)
    run_child([sys.executable, "-m", "venv", "--without-pip", venv], env=env)
    py = venv / "bin" / "python"
    pins = [f"torch=={__import__('torch').__version__.split('+')[0]}"]
    house = wheelhouse(built["wheel"], EXTRAS, pins)
    run_child(
        [sys.executable, "-m", "pip", "--python", py, "install", "--quiet", "--no-compile",
         "--no-index", "--find-links", house, *pins, f"{built['wheel']}[{EXTRAS}]"],
        env=env, timeout=600,
    )  # fmt: skip
    work = tmp / "elsewhere"
    work.mkdir()
    return {"py": py, "exe": venv / "bin" / "torchcontact", "venv": venv, "work": work, "env": env}


def test_installed_wheel_imports_every_subpackage_from_the_venv(installed, built):
    packages = sorted(source_packages(built["src"]))
    code = (
        "import importlib, sys\nfor n in sys.argv[1:]: print(importlib.import_module(n).__file__)"
    )
    files = run_child(
        [installed["py"], "-c", code, *packages], cwd=installed["work"], env=installed["env"]
    ).split()
    assert len(files) == len(packages)
    outside = [f for f in files if not f.startswith(str(installed["venv"]))]
    assert not outside, f"imported from outside the venv (not the installed wheel): {outside}"
    out = run_child([installed["exe"], "--version"], cwd=installed["work"], env=installed["env"])
    assert out.strip() == torchcontact.__version__


def test_installed_console_script_runs_demo_export_and_train(installed):
    """Three commands of the installed console script, each in its own process. They are
    independent, so they run at once (the suite's time: mostly each process's imports)."""
    from concurrent.futures import ThreadPoolExecutor

    work, env = installed["work"], installed["env"]
    (work / "tiny.toml").write_text(TINY_CONFIG)
    commands = {
        "demo": ("demo", "--frames", "60", "--out", "demo", "--quiet"),
        "export": ("export", "estimator", "--robot", "tcarm", "--slot", "hand_skin:force",
                   "--out", "e.onnx"),
        "train": ("train", "fit", "--config", "tiny.toml", "--out", "ckpt"),
    }  # fmt: skip
    with ThreadPoolExecutor(len(commands)) as pool:
        runs = {k: pool.submit(run_child, [installed["exe"], *a], cwd=work, env=env)
                for k, a in commands.items()}  # fmt: skip
        out = {k: f.result() for k, f in runs.items()}  # a child's failure fails the test
    assert "estimates:" in out["demo"]
    for f in ("log.parquet", "estimate.parquet", "forces.png", "quality.png"):
        assert (work / "demo" / f).stat().st_size > 0, f
    assert (work / "e.onnx").stat().st_size > 0 and (work / "e.step.onnx").stat().st_size > 0
    assert "checkpoint: ckpt" in out["train"]
    meta = json.loads((work / "ckpt" / "checkpoint.json").read_text())
    assert meta["sensor"] == "base_ft" and (work / "ckpt" / "weights.safetensors").is_file()


def test_a_failing_child_shows_its_stderr(tmp_path):
    with pytest.raises(pytest.fail.Exception) as e:
        run_child([sys.executable, "-c", "import sys; sys.exit('boom on stderr')"], cwd=tmp_path)
    assert "exited with 1" in str(e.value) and "boom on stderr" in str(e.value)
