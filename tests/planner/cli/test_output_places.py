"""Output places (issue 28): system file systems, a full disk, read-only places and files in the way are typed errors
naming the user's path with nothing left behind; a file reachplan did not write is never replaced; one run at a time
per place; SIGTERM and SIGHUP clean up like Ctrl-C; staging folders of killed runs are removed by the next run."""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import io
import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reachplan.imaging import places
from reachplan.imaging.errors import OutputExistsError, OutputPlaceError
from reachplan.imaging.files import MANIFEST, atomic_write_bytes, read_manifest, written_by_reachplan
from reachplan.imaging.phantom import PhantomFiles, phantom_spec, write_phantom
from reachplan.imaging.places import check_place, lock_place, place_error, release_places, remove_stale_stages
from reachplan.planner.cli import main
from reachplan.planner.cli.edges import Interrupted, interruptible, staged_folder

HDR = ("tps_examples/hdr/RP.HDR.dcm", "tps_examples/hdr/RS.HDR.dcm")


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err, err
    return code, err


def _error(err: str, command: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ": warning: " not in ln]
    assert len(lines) == 1 and lines[0].startswith(f"reachplan {command}: error:"), err
    return lines[0]


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _no_space(*args: object) -> None:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> PhantomFiles:
    return write_phantom(tmp_path_factory.mktemp("case"))


@pytest.fixture
def dose_args(reference_file: Callable[[str], Path]) -> list[str]:
    rp, rs = (reference_file(f) for f in HDR)
    return ["dose", "--plan", str(rp), "--structures", str(rs), "--spacing", "8", "--margin", "10", "--quiet"]


# --- places that cannot hold output: refused before any work, naming the user's path ------------------------------


@pytest.mark.parametrize("place", ["/proc/reachplan_out", "/proc/self/out", "/sys/reachplan_out", "/dev/reachplan"])
def test_system_file_systems_are_refused_before_any_work(place: str, case: PhantomFiles, dose_args: list[str],
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("the kernel's file systems of Linux")
    commands = {
        "plan": ["plan", "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030", "--quiet",
                 "--out", place],
        "dose": [*dose_args, "--out", f"{place}/RD.dcm"],
        "phantom": ["phantom", "--case", "pilot", "--quiet", "--out", place],
        "demo": ["demo", "--quiet", "--out", place],
    }
    for command, args in commands.items():
        code, err = _run(args, capsys)
        line = _error(err, command)
        assert code == 2 and f"--out {place}" in line and "system file system" in line and ".staging" not in line


def test_a_file_where_a_folder_is_expected(case: PhantomFiles, dose_args: list[str], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for command, args in {
        "plan": ["plan", "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030", "--quiet"],
        "dose": dose_args, "phantom": ["phantom", "--case", "pilot", "--quiet"],
    }.items():
        code, err = _run([*args, "--out", str(blocker / "sub" / "out")], capsys)
        assert code == 2 and "is a file, not a folder" in _error(err, command)
    # found only when the staged files move in: out/export is a file; nothing moves, the stage is gone
    out = tmp_path / "out"
    out.mkdir()
    (out / "export").write_text("in the way")
    with pytest.raises(OutputPlaceError, match=r"out/export is a file where reachplan writes a folder"), \
            staged_folder(out) as stage:
        (stage / "plan.json").write_text("{}")
        (stage / "export").mkdir()
        (stage / "export" / "RP.dcm").write_text("new")
    assert _tree(tmp_path) == ["file", "out", "out/export"] and (out / "export").read_text() == "in the way"


def test_read_only_and_full_places_are_refused_before_any_work(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    class ReadOnly:
        f_flag = os.ST_RDONLY

    with monkeypatch.context() as m:  # a read-only mount (root cannot write there either)
        m.setattr(os, "statvfs", lambda path: ReadOnly())
        with pytest.raises(OutputPlaceError, match=r"^--out given/out: .* is on a read-only file system"):
            check_place(tmp_path / "out", Path("given/out"), "--out", folder=True, need_mb=1)
    with monkeypatch.context() as m:
        m.setattr("shutil.disk_usage", lambda path: type("U", (), {"free": 3_000_000})())
        with pytest.raises(OutputPlaceError, match=r"has 3.0 MB free; the output needs about 50 MB"):
            check_place(tmp_path / "out", tmp_path / "out", "--out", folder=True, need_mb=50)
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_folder_by_its_permissions(case: PhantomFiles, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    if os.access(locked, os.W_OK):  # root writes anyway (CI runs as root): the permission check is what is tested
        real_access = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == locked and mode & os.W_OK
                            else real_access(p, mode, **kw))
    try:
        code, err = _run(["plan", "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030", "--quiet",
                          "--out", str(locked / "out")], capsys)
        assert code == 2 and "is not writable" in _error(err, "plan") and ".staging" not in err
    finally:
        locked.chmod(0o755)


# --- a full disk while writing: a typed error, nothing left --------------------------------------------------------


def test_dose_on_a_full_disk_leaves_no_file_and_no_folder(dose_args: list[str], tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    full = tmp_path / "full"
    full.mkdir()
    monkeypatch.setattr(os, "fsync", _no_space)  # a full disk shows at the latest when the data is flushed
    code, err = _run([*dose_args, "--out", str(full / "sub" / "RD.dcm")], capsys)
    line = _error(err, "dose")
    assert code == 2 and f"--out {full / 'sub' / 'RD.dcm'}: no space left on the device" in line
    assert "free some space" in line and ".tmp" not in line
    assert _tree(tmp_path) == ["full"]  # no sub/, no temporary file


def test_phantom_on_a_full_disk_leaves_no_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(os, "fsync", _no_space)
    code, err = _run(["phantom", "--case", "pilot", "--quiet", "--out", str(tmp_path / "new" / "case")], capsys)
    assert code == 2 and "no space left on the device" in _error(err, "phantom")
    assert _tree(tmp_path) == []


@pytest.mark.parametrize(("err", "match"), [(errno.ENOSPC, "no space left on the device"),
                                            (errno.EROFS, "the file system is read-only"),
                                            (errno.EACCES, "cannot write there")])
def test_a_failure_of_the_place_while_staging_names_the_users_path(tmp_path: Path, err: int, match: str) -> None:
    given = tmp_path / "a" / "out"
    with pytest.raises(OutputPlaceError) as exc, staged_folder(given) as stage:
        (stage / "plan.json").write_text("{}")
        raise OSError(err, os.strerror(err), str(stage / "report.html"))
    assert str(exc.value).startswith(f"--out {given}: {match}") and "staging" not in str(exc.value)
    assert _tree(tmp_path) == []  # the stage and the folders made for it are gone


def test_a_full_disk_under_a_command_that_writes_in_place_is_a_typed_error(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    import reachplan.planner.cli.bench as bench_cli

    def full(args: argparse.Namespace) -> int:  # a study's or benchmark's files are written in place
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(args.out / "parts" / "x.json"))

    monkeypatch.setattr(bench_cli, "run", full)
    code, err = _run(["bench", "models", "--out", str(tmp_path / "b")], capsys)
    assert code == 2 and _error(err, "bench").endswith(f"--out {tmp_path / 'b'}: no space left on the device; "
                                                       "nothing was written: free some space or choose another "
                                                       "output place")


def test_an_error_of_an_input_is_not_taken_for_the_place(tmp_path: Path) -> None:
    with pytest.raises(PermissionError), staged_folder(tmp_path / "out"):
        raise PermissionError(errno.EACCES, "Permission denied", "/somewhere/else/CT.dcm")
    assert _tree(tmp_path) == []


# --- never overwrite a file reachplan did not write ----------------------------------------------------------------


def test_phantom_leaves_a_foreign_case_json_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "case"
    out.mkdir()
    (out / "case.json").write_text('{"mine": true}\n')
    code, err = _run(["phantom", "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "case.json" in _error(err, "phantom") and "refusing to overwrite" in err
    assert _tree(out) == ["case.json"] and (out / "case.json").read_text() == '{"mine": true}\n'


def test_a_case_replaces_the_files_it_wrote_and_only_those(tmp_path: Path) -> None:
    out = tmp_path / "case"
    small = dataclasses.replace(phantom_spec(), slice_thickness_mm=30.0, pixel_mm=8.0, matrix=32)  # 7 slices
    for about in (b'{"run": 1}', b'{"run": 2}'):  # the second run replaces what the first one wrote
        files = write_phantom(out, small, beside={"case.json": about})
        assert (out / "case.json").read_bytes() == about
    recorded = read_manifest(out)
    assert {"case.json", "RS.phantom.dcm", f"CT/{sorted(files.ct_dir.iterdir())[0].name}"} <= set(recorded)
    (out / "case.json").write_text('{"edited": true}\n')  # changed since reachplan wrote it: not ours any more
    with pytest.raises(OutputExistsError, match=r"case\.json"):
        write_phantom(out, small, beside={"case.json": b"{}"})
    assert (out / "case.json").read_text() == '{"edited": true}\n'


def test_plan_refuses_a_foreign_report_before_the_work(case: PhantomFiles, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.html").write_text("my report")
    code, err = _run(["plan", "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030", "--quiet",
                      "--out", str(out)], capsys)
    assert code == 2 and f"{out / 'report.html'} exists and was not written by reachplan" in _error(err, "plan")
    assert _tree(tmp_path) == ["out", "out/report.html"] and (out / "report.html").read_text() == "my report"


def test_dose_refuses_a_foreign_file_before_any_work_and_replaces_its_own(dose_args: list[str], tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    rd = tmp_path / "RD.dcm"
    rd.write_bytes(b"a TPS's dose")
    code, err = _run([*dose_args, "--out", str(rd)], capsys)
    assert code == 2 and "was not written by reachplan" in _error(err, "dose") and rd.read_bytes() == b"a TPS's dose"
    rd.unlink()
    for _ in range(2):
        code, _ = _run([*dose_args, "--out", str(rd)], capsys)
        assert code == 0 and written_by_reachplan(rd)
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST, "RD.dcm"]


def test_a_staged_commit_checks_every_file_before_moving_any(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with staged_folder(out) as stage:  # the first run: recorded
        (stage / "plan.json").write_text("1")
        (stage / "export").mkdir()
        (stage / "export" / "RP.dcm").write_text("1")
    assert written_by_reachplan(out / "export" / "RP.dcm") and (out / "plan.json").stat().st_mode & 0o777 != 0o700
    (out / "report.html").write_text("the user's own report")
    with pytest.raises(OutputExistsError, match=r"out/report.html exists and was not written by reachplan"), \
            staged_folder(out) as stage:
        for name in ("plan.json", "report.html"):
            (stage / name).write_text("2")
    assert (out / "plan.json").read_text() == "1" and (out / "report.html").read_text() == "the user's own report"
    assert _tree(tmp_path) == ["out", f"out/{MANIFEST}", "out/export", "out/export/RP.dcm", "out/plan.json",
                               "out/report.html"]
    atomic_write_bytes(out / "export" / "RP.dcm", b"edited by hand")
    assert not written_by_reachplan(out / "export" / "RP.dcm")


NAMES = ["plan.json", "report.html", "export/RP.dcm", "export/implant_steered/device.json", "phantom/CT/CT.0001.dcm"]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@settings(max_examples=40, deadline=None)
@given(st.dictionaries(st.sampled_from(NAMES), st.sampled_from(["ours", "foreign", "edited"]), max_size=4),
       st.sets(st.sampled_from(NAMES), min_size=1, max_size=4))
def test_a_commit_replaces_what_reachplan_wrote_and_nothing_else(existing: dict[str, str], staged: set[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        with places.staged_folder(out) as stage:  # an earlier run
            for name, kind in existing.items():
                (stage / name).parent.mkdir(parents=True, exist_ok=True)
                (stage / name).write_bytes(b"old" if kind != "foreign" else b"")
        for name, kind in existing.items():
            if kind != "ours":
                (out / name).write_bytes(kind.encode())  # written by someone else, or edited since
        before = _snapshot(out)
        blocking = sorted(n for n in staged if existing.get(n) in ("foreign", "edited"))
        try:
            with places.staged_folder(out) as stage:
                for name in staged:
                    (stage / name).parent.mkdir(parents=True, exist_ok=True)
                    (stage / name).write_bytes(b"new")
        except OutputExistsError as exc:
            assert blocking and any(str(out / n) in str(exc) for n in blocking)
            assert _snapshot(out) == before  # nothing moved
        else:
            assert not blocking
            assert all((out / n).read_bytes() == b"new" and written_by_reachplan(out / n) for n in staged)
            assert all((out / n).read_bytes() == before[n] for n in existing if n not in staged)
        assert [p.name for p in Path(tmp).iterdir()] == ["out"]  # no staging folder left


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(sorted(errno.errorcode)), st.sampled_from(["stage", "out", "elsewhere", None]))
def test_an_os_error_becomes_a_typed_error_only_about_the_place_and_never_names_the_stage(code: int,
                                                                                        where: str | None) -> None:
    stage, out = Path("/data/.out.1-ab.staging"), Path("/data/out")
    filename = {"stage": stage / "export" / "RP.dcm", "out": out / "plan.json", "elsewhere": Path("/in/CT.dcm"),
                None: None}[where]
    exc = OSError(code, os.strerror(code), *([] if filename is None else [str(filename)]))
    typed = place_error(exc, Path("out"), "--out", (stage, out))
    place = code in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)
    assert (typed is not None) == (place or (where != "elsewhere" and code in (
        errno.EACCES, errno.EPERM, errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENOTEMPTY,
        errno.EXDEV, errno.EINVAL)))
    if typed is not None:
        assert str(typed).startswith("--out out: ") and "staging" not in str(typed) and "\n" not in str(typed)


def test_an_interrupted_run_stops_the_background_compile(monkeypatch: pytest.MonkeyPatch) -> None:
    from reachplan.planner import kernels

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    monkeypatch.setattr(kernels, "_child", kernels._Child(child, Path("unused")))
    kernels.stop()
    assert child.poll() is not None


# --- runs: locks, stale staging folders, signals --------------------------------------------------------------------


def test_stale_staging_folders_of_dead_runs_are_removed_with_a_line(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True).stdout.strip()
    stale = [tmp_path / f".out.{dead}-0a1b2c3d.staging", tmp_path / ".out.k2j3h4g5.staging"]  # dead; an old name
    live = tmp_path / f".out.{os.getppid()}-0a1b2c3d.staging"
    other = tmp_path / f".out2.{dead}-0a1b2c3d.staging"
    for folder in [*stale, live, other]:
        (folder / "CT").mkdir(parents=True)
    with staged_folder(out) as stage:
        (stage / "plan.json").write_text("{}")
    err = capsys.readouterr().err
    assert all(f"removed {p}, a staging folder left by an interrupted run" in err for p in stale)
    assert f"(process {dead})" in err and str(live) not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name, "out"])
    assert remove_stale_stages(out.resolve()) == []


def test_sigterm_and_sighup_raise_like_ctrl_c_and_the_handlers_come_back() -> None:
    before = signal.getsignal(signal.SIGTERM)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        with pytest.raises(Interrupted) as exc, interruptible():
            os.kill(os.getpid(), sig)
            time.sleep(5)  # interrupted at once
        assert exc.value.signum == sig and isinstance(exc.value, KeyboardInterrupt)
    assert signal.getsignal(signal.SIGTERM) == before
    hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup: the run must outlive the terminal
    try:
        with interruptible():
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(0.05)
            assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, hup)


def test_a_lock_is_held_once_per_place_and_released(tmp_path: Path) -> None:
    script = ("import sys; from pathlib import Path; from reachplan.imaging.places import lock_place; "
              "lock_place(Path(sys.argv[1]), Path('x'), '--out'); print('locked')")
    lock_place(tmp_path, tmp_path, "--out")
    lock_place(tmp_path, tmp_path, "--out")  # the same process again: nothing
    other = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True)
    assert other.returncode == 1 and "OutputBusyError" in other.stderr
    assert f"another reachplan run (process {os.getpid()}) is writing there" in other.stderr
    release_places()
    other = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True)
    assert other.returncode == 0 and other.stdout.strip() == "locked"
    lock = places._lock_folder() / f"{hashlib.sha256(str(tmp_path).encode()).hexdigest()[:32]}.lock"
    assert not lock.exists()  # removed when the process ended, though it never released the lock itself


def _reachplan(*args: str) -> subprocess.Popen[str]:
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")  # no background compile: the run is stopped early
    return subprocess.Popen([sys.executable, "-m", "reachplan.planner.cli", *args], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _wait_for_stage(parent: Path, proc: subprocess.Popen[str]) -> None:
    t0 = time.perf_counter()
    while not list(parent.glob(".out.*.staging")):
        assert proc.poll() is None, proc.communicate()
        assert time.perf_counter() - t0 < 60, "no staging folder appeared"
        time.sleep(0.05)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129), (signal.SIGKILL, -9)])
def test_a_second_run_fails_at_once_and_a_signal_leaves_no_staging(tmp_path: Path, sig: int, code: int) -> None:
    out = tmp_path / "out"
    first = _reachplan("demo", "--out", str(out), "--quiet")
    try:
        _wait_for_stage(tmp_path, first)
        if sig == signal.SIGTERM:  # the lock: the second run into the same folder fails before any work
            t = time.perf_counter()
            second = subprocess.run([sys.executable, "-m", "reachplan.planner.cli", "demo", "--out", str(out)],
                                    capture_output=True, text=True, timeout=60)
            assert second.returncode == 2 and time.perf_counter() - t < 10
            assert f"another reachplan run (process {first.pid}) is writing there" in second.stderr
        first.send_signal(sig)
        _, err = first.communicate(timeout=60)
    finally:
        first.kill()
    assert first.returncode == code, err
    if sig == signal.SIGKILL:  # no clean-up possible: the next run into the place removes the staging folder
        (stage,) = tmp_path.glob(".out.*.staging")
        after = _reachplan("demo", "--case", "pilot", "--seed", "1", "--out", str(out))  # fails once staged
        _, err = after.communicate(timeout=60)
        assert after.returncode == 2 and f"removed {stage}, a staging folder left by an interrupted run (process " \
            f"{first.pid})" in err
    assert list(tmp_path.iterdir()) == []  # no staging folder, no output folder


# --- progress: a bar moves during a long step -------------------------------------------------------------------


def test_a_bar_keeps_moving_during_a_long_step_and_a_quiet_one_starts_no_thread() -> None:
    from reachplan.planner.report.progress import MovingBar, spinner

    sink = io.StringIO()
    bar = MovingBar(total=4, desc="delivery", file=sink, every_s=0.05, mininterval=0)
    time.sleep(0.5)  # one step of the work, no update
    drawn = sink.getvalue().count("\r")
    bar.close()
    assert drawn >= 5 and "0/4" in sink.getvalue()  # redrawn while the step ran (its elapsed time moving)
    with spinner("delivery", quiet=True) as quiet_bar:
        assert quiet_bar._ticker is None


def test_libraries_that_swallow_an_interrupt_are_imported_before_the_command_runs(tmp_path: Path) -> None:
    """trimesh wraps its optional imports in ``except BaseException``: a SIGTERM or Ctrl-C arriving while it imports
    was swallowed and the demo went on. The CLI imports it before the command (and its signal handlers) run."""
    code = ("import sys\n"
            "import reachplan.planner.cli.demo as demo\n"
            "demo.run = lambda args: print('trimesh' in sys.modules) or 0\n"
            "from reachplan.planner.cli import main\n"
            f"sys.exit(main(['demo', '--out', {str(tmp_path / 'out')!r}]))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"
