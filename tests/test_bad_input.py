"""Every command under bad input: exit 2, one line naming the value and the fix, no traceback, nothing overwritten.

A table of cases (command, flags) runs each command in this process through
``dronecal_field.cli.main``. The inputs are tiny files of every kind a tired
user may pass by mistake (missing, a folder, empty, garbage text, binary,
Latin-1 instead of UTF-8), every numeric flag at 0, negative, NaN, inf and
absurdly large, output paths that are files, read-only or under a missing
folder, and addresses that are malformed or unreachable. Nothing here flies,
calibrates or serves for real: each case must be refused before that, which
is what makes the file fast. A case that runs past its timeout fails (the
command accepted the value and started working).
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import traceback
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from dronecal_field.cli import main

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "missions" / "paper-pinhole" / "mission.plan"
SITE = ROOT / "missions" / "paper-pinhole.toml"
TRUTH = ROOT / "replays" / "nominal.truth.yaml"
SURVEY_PARQUET = ROOT / "tests" / "data" / "survey_small.parquet"
CASE_TIMEOUT_S = 60  # a refusal takes well under a second; this only stops a command that started real work


# --------------------------------------------------------------------------
# the files a user may pass by mistake


def _camera_text(**replace: str) -> str:
    text = TRUTH.read_text()
    for old, new in replace.items():
        text = text.replace(old.replace("_SPACE_", " "), new)
    return text


def _points_csv(n_grid: int = 5) -> str:
    """x,y,z of points the truth camera sees at two depths (enough to calibrate)."""
    from dronecal_field.camerafile import read_camera

    cam = read_camera(TRUTH)
    i = cam.intrinsics
    us, vs = np.meshgrid(np.linspace(60, i.width - 60, n_grid), np.linspace(40, i.height - 40, n_grid))
    rays = np.stack([(us.ravel() - i.cx) / i.fx, (vs.ravel() - i.cy) / i.fy, np.ones(us.size)], axis=1)
    R = cam.pose.R_cam_from_world
    c = cam.pose.position_world
    rows = [c + d * (R.T @ r) for d in (6.0, 11.0) for r in rays]
    return "x,y,z\n" + "".join(f"{x:.4f},{y:.4f},{z:.4f}\n" for x, y, z in rows)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    return make_files(tmp_path_factory.mktemp("bad"))


def make_files(d: Path) -> dict[str, str]:
    """The bad (and a few good) inputs in folder ``d``; placeholder name -> path."""
    p: dict[str, Path] = {
        "missing": d / "no-such-file.yaml",
        "dir": d / "a-folder",
        "empty": d / "empty.txt",
        "garbage": d / "garbage.txt",
        "binary": d / "binary.bin",
        "latin1": d / "latin1.txt",
        "camera": d / "camera.yaml",
        "cam_focal0": d / "camera-focal0.yaml",
        "cam_negfocal": d / "camera-negfocal.yaml",
        "cam_nan": d / "camera-nan.yaml",
        "cam_rot": d / "camera-rot.yaml",
        "cam_size0": d / "camera-size0.yaml",
        "points": d / "points.csv",
        "points_nan": d / "points-nan.csv",
        "points_behind": d / "points-behind.csv",
        "points_flat": d / "points-flat.csv",
        "points_few": d / "points-few.csv",
        "points_huge": d / "points-huge.csv",
        "mission": d / "mission.plan",
        "mission_latin1": d / "mission-latin1.plan",
        "mission_bad": d / "mission-bad.plan",
        "out_file": d / "existing-output.txt",
        "run_existing": d / "run.mcap",
        "tlog_garbage": d / "flight.tlog",
        "results_bad": d / "results-bad.parquet",
        "results_cut": d / "results-cut.parquet",
        "noparent": d / "no-such-folder" / "out",
    }
    p["dir"].mkdir()
    p["empty"].write_bytes(b"")
    p["garbage"].write_text("this is not what you think it is\n{[}\n" * 3)
    p["binary"].write_bytes(bytes(range(256)) * 8)
    p["latin1"].write_bytes("x,y,z\n1,2,3 # caf\xe9\n".encode("latin-1"))
    p["camera"].write_text(_camera_text())
    p["cam_focal0"].write_text(_camera_text(**{"500., 0., 319.5, 0., 500.": "0., 0., 319.5, 0., 0."}))
    p["cam_negfocal"].write_text(_camera_text(**{"500., 0., 319.5, 0., 500.": "-500., 0., 319.5, 0., -500."}))
    p["cam_nan"].write_text(_camera_text(**{"319.5": ".nan"}))
    p["cam_rot"].write_text(_camera_text(**{"0.86602540378443871": "5.0"}))
    p["cam_size0"].write_text(_camera_text(**{"image_width: 640": "image_width: 0"}))
    good = _points_csv()
    p["points"].write_text(good)
    p["points_nan"].write_text(good + "nan,1,2\n")
    p["points_behind"].write_text("x,y,z\n" + "".join(f"{x},{-20 - y},{z}\n" for x in (-2, 0, 2) for y in (0, 3) for z in (0, 1)))
    p["points_flat"].write_text("x,y,z\n" + "".join(f"{x},{8 + y},0\n" for x in range(-3, 4) for y in range(4)))
    p["points_few"].write_text("x,y,z\n1,8,0\n2,9,1\n")
    # 300 000 points (9 MB): no calibration needs this many; it must be refused, not exhaust memory
    p["points_huge"].write_text(good + good.split("\n", 1)[1] * 6000)
    shutil.copy(MISSION, p["mission"])
    p["mission_latin1"].write_bytes(MISSION.read_bytes().replace(b'"fileType"', b'"fileType\xe9"', 1))
    p["mission_bad"].write_text('{"fileType": "Plan", "mission": {"items": [{"type": "SimpleItem", "command": "x"}]}}')
    p["out_file"].write_text("keep me\n")
    p["run_existing"].write_bytes(b"an earlier flight" * 64)
    p["tlog_garbage"].write_bytes(bytes(range(256)) * 4)
    p["results_bad"].mkdir()
    (p["results_bad"] / "part-0.parquet").write_bytes(b"PAR1 not really")
    shutil.copytree(SURVEY_PARQUET, p["results_cut"]) if SURVEY_PARQUET.is_dir() else shutil.copy(SURVEY_PARQUET, p["results_cut"])
    for part in sorted(Path(p["results_cut"]).glob("*.parquet")) if p["results_cut"].is_dir() else [p["results_cut"]]:
        data = part.read_bytes()
        part.write_bytes(data[: len(data) // 2])
        break
    ro = d / "read-only"
    ro.mkdir()
    ro.chmod(0o555)
    # root ignores permission bits: /sys refuses writes even to root
    p["ro"] = (ro if os.geteuid() != 0 else Path("/sys")) / "out"
    out = {k: str(v) for k, v in p.items()}
    out["root"] = str(d)
    out["site"] = str(SITE)
    return out


def _snapshot(root: str) -> dict[str, str]:
    """Every file under ``root`` with the hash of its bytes."""
    snap = {}
    for path in sorted(Path(root).rglob("*")):
        if path.is_file():
            snap[str(path.relative_to(root))] = hashlib.sha1(path.read_bytes()).hexdigest()
        elif path.is_dir():
            snap[str(path.relative_to(root)) + "/"] = "dir"
    return snap


# --------------------------------------------------------------------------
# the table: (case id, argv with {placeholders}, text the one line must contain)

BAD_NUMBERS = ("0", "-1", "nan", "inf", "1e300")


def _numeric(prefix: list[str], flag: str, values: tuple[str, ...] = BAD_NUMBERS, suffix: tuple[str, ...] = ()) -> list:
    command = " ".join(prefix[:2]) if prefix[0] == "sim" else prefix[0]
    named = RENAMED.get(flag, flag)  # an old name is answered with the new one
    return [(f"{command} {flag} {v}", [*prefix, f"{flag}={v}", *suffix], named) for v in values]


# Old flag names kept hidden for one release -> the name the error line uses.
RENAMED = {"--sigma-2d": "--sigma-px", "--noise-px": "--noise-dn", "--duration": "--duration-s", "--geoid-sep": "--geoid-separation"}


FILE_KINDS = ("missing", "dir", "empty", "garbage", "binary", "latin1")

UNC = ["uncertainty", "--camera", "{camera}", "--points", "{points}"]
CAL = ["calibrate", "{run_existing}"]
FLY = ["fly", "--connect", "udp:127.0.0.1:9", "--mission", "{mission}", "--video", "http://127.0.0.1:9/x.mjpg",
       "--marker-size", "0.3", "--heartbeat-timeout", "0.3", "--dry-run"]
FLY_OUT = ["--out", "{root}/fly-run.mcap"]
IMP = ["import", "--tlog", "{tlog_garbage}", "--image-size", "640x360", "--marker-dictionary", "DICT_4X4_50", "--marker-id", "0", "--marker-size", "0.3"]
IMP_OUT = ["--out", "{root}/imported.mcap"]
SV = ["sim", "vehicle", "--listen", "udp:127.0.0.1:0", "--home", "-35.36,149.16,584", "--duration-s", "1"]
SC = ["sim", "camera", "--connect", "udpin:127.0.0.1:0", "--camera", "{camera}", "--serve", "http://127.0.0.1:0/s.mjpg", "--duration-s", "1"]
SCS = ["sim", "camera", "--connect", "udpin:127.0.0.1:0", "--site-lat", "-35.36", "--site-lon", "149.16", "--site-h", "584",
       "--serve", "http://127.0.0.1:0/s.mjpg", "--duration-s", "1"]
SUR = ["survey", "--cameras", "2", "--trials", "2", "--workers", "0", "--no-progress", "--out", "{root}/survey-new.parquet"]
PLAN = ["plan", "--site", "{site}", "--out", "{root}/plan-out"]
DEMO = ["demo", "--out", "{root}/demo-out"]


def _cases() -> list[tuple[str, list[str], str]]:
    c: list[tuple[str, list[str], str]] = []
    # ---- uncertainty
    for kind in FILE_KINDS:
        c.append((f"uncertainty --camera {kind}", ["uncertainty", "--camera", "{" + kind + "}", "--points", "{points}"], "{" + kind + "}"))
        c.append((f"uncertainty --points {kind}", ["uncertainty", "--camera", "{camera}", "--points", "{" + kind + "}"], "{" + kind + "}"))
    for cam in ("cam_focal0", "cam_negfocal", "cam_nan", "cam_rot", "cam_size0"):
        c.append((f"uncertainty --camera {cam}", ["uncertainty", "--camera", "{" + cam + "}", "--points", "{points}"], "{" + cam + "}"))
    for pts, needle in (("points_nan", "nan"), ("points_behind", "behind"), ("points_flat", "coplanar"), ("points_few", "points"), ("points_huge", "100000 points")):
        c.append((f"uncertainty --points {pts}", ["uncertainty", "--camera", "{camera}", "--points", "{" + pts + "}"], needle))
    c += _numeric(UNC, "--trials", ("0", "1", "-1", "100000000"))
    c += _numeric(UNC, "--sigma-px", ("-1", "nan", "inf", "1e300"))
    c += _numeric(UNC, "--sigma-2d", ("-1",))
    c += _numeric(UNC, "--sigma-3d", ("-1", "nan", "inf", "1e300", "1,2", "a,b,c"))
    c += _numeric(UNC, "--seed", ("-1",))
    c.append(("uncertainty --model bogus", [*UNC, "--model", "bogus"], "bogus"))
    c.append(("uncertainty --plot-convergence missing folder", [*UNC, "--plot-convergence", "{noparent}.png"], "--plot-convergence"))
    c.append(("uncertainty --plot-convergence folder", [*UNC, "--plot-convergence", "{dir}"], "--plot-convergence"))
    c.append(("uncertainty --plot-convergence read-only", [*UNC, "--plot-convergence", "{ro}.png"], "--plot-convergence"))
    # ---- calibrate
    for kind in FILE_KINDS:
        c.append((f"calibrate run {kind}", ["calibrate", "{" + kind + "}", "--out", "{root}/cal-out"], "{" + kind + "}"))
    c += _numeric(CAL, "--loss-scale-px", ("0", "-1", "nan", "inf"))
    c += _numeric(CAL, "--trials", ("1", "-1"))
    c += _numeric(CAL, "--settle-s", ("-1", "nan", "inf", "1e300"))
    c += _numeric(CAL, "--max-frames-per-window", ("0", "-1"))
    c += _numeric(CAL, "--max-readout-s", ("-1", "nan", "inf", "1"))
    c += _numeric(CAL, "--workers", ("-1",))
    c += _numeric(CAL, "--seed", ("-1",))
    c.append(("calibrate --out file", [*CAL, "--out", "{out_file}"], "--out"))
    c.append(("calibrate --out missing parent", [*CAL, "--out", "{noparent}/deeper"], "--out"))
    c.append(("calibrate --out read-only", [*CAL, "--out", "{ro}"], "--out"))
    c.append(("calibrate batch without --out", ["calibrate", "{run_existing}", "{run_existing}"], "--out"))
    # ---- fly (pre-flight: nothing is uploaded; the flags are checked before the link opens)
    for kind in FILE_KINDS:
        c.append((f"fly --mission {kind}", ["fly", "--connect", "udp:127.0.0.1:9", "--mission", "{" + kind + "}", "--video", "x.mp4",
                                            "--marker-size", "0.3", *FLY_OUT], "{" + kind + "}"))
    c.append(("fly --mission latin1", [*FLY[:4], "{mission_latin1}", *FLY[5:], *FLY_OUT], "{mission_latin1}"))
    c.append(("fly --mission bad item", [*FLY[:4], "{mission_bad}", *FLY[5:], *FLY_OUT], "{mission_bad}"))
    for flag, values in (("--baud", ("0", "-1")), ("--heartbeat-timeout", ("0", "-1", "nan", "inf")), ("--link-timeout", ("0", "-1", "nan", "inf")),
                         ("--timeout-s", ("0", "-1", "nan")), ("--min-battery", ("-1", "101")), ("--max-home-distance", ("0", "-1", "nan")),
                         ("--ready-timeout", ("-1", "nan", "inf")), ("--camera-width", ("0", "-1")), ("--camera-height", ("0", "-1")),
                         ("--camera-latency", ("-1", "nan", "inf")), ("--frame-queue", ("0", "-1")), ("--marker-size", ("0", "-1", "nan", "inf")),
                         ("--marker-id", ("-1", "999")), ("--marker-offset", ("nan,0,0", "1,2", "inf,0,0"))):
        c += _numeric(FLY, flag, values, tuple(FLY_OUT))
    c.append(("fly --marker-dictionary bogus", [*FLY, "--marker-dictionary", "DICT_BOGUS", *FLY_OUT], "--marker-dictionary"))
    for url in ("bogus", "udp:127.0.0.1", "udp:127.0.0.1:99999", "tcp:256.1.1.1:5760", "udp:[bad:1", "serial:"):
        c.append((f"fly --connect {url}", ["fly", "--connect", url, *FLY[3:], *FLY_OUT], url))
    c.append(("fly unreachable vehicle", [*FLY, *FLY_OUT], "heartbeat"))
    c.append(("fly --video http://[bad", ["fly", "--connect", "udp:127.0.0.1:9", "--mission", "{mission}", "--video", "http://[bad",
                                          "--marker-size", "0.3", *FLY_OUT], "http://[bad"))
    c.append(("fly --out existing run", ["fly", "--connect", "udp:127.0.0.1:9", "--mission", "{mission}", "--video", "x.mp4",
                                         "--marker-size", "0.3", "--out", "{run_existing}"], "run.mcap"))
    c.append(("fly --out missing folder", [*FLY, "--out", "{noparent}/run.mcap"], "--out"))
    c.append(("fly --out folder", ["fly", "--connect", "udp:127.0.0.1:9", "--mission", "{mission}", "--video", "x.mp4",
                                   "--marker-size", "0.3", "--out", "{dir}"], "--out"))
    # ---- import
    for kind in FILE_KINDS:
        c.append((f"import --tlog {kind}", ["import", "--tlog", "{" + kind + "}", *IMP[3:], *IMP_OUT], "{" + kind + "}"))
        c.append((f"import --bin {kind}", ["import", "--bin", "{" + kind + "}", *IMP[3:], *IMP_OUT], "{" + kind + "}"))
    for kind in ("missing", "dir"):  # a video's content is read after the log, which needs a real flight
        c.append((f"import --video {kind}", [*IMP, "--video", "{" + kind + "}", *IMP_OUT], "{" + kind + "}"))
    for size in ("0x0", "-1x5", "640", "axb", "100000x100000"):
        c.append((f"import --image-size {size}", [*IMP[:3], "--image-size", size, *IMP[5:], *IMP_OUT], "--image-size"))
    for flag, values in (("--marker-size", ("0", "-1", "nan", "inf")), ("--marker-id", ("-1", "999")), ("--marker-offset", ("nan,0,0", "1,2", "inf,0,0")),
                        ("--max-fps", ("0", "-1", "nan", "inf")), ("--jpeg-quality", ("-1", "101"))):
        c += _numeric(IMP, flag, values, tuple(IMP_OUT))
    c.append(("import --marker-dictionary bogus", [*IMP, "--marker-dictionary", "DICT_BOGUS", *IMP_OUT], "--marker-dictionary"))
    c.append(("import --video-start bogus", [*IMP, "--video-start", "yesterday", *IMP_OUT], "--video-start"))
    c.append(("import --out existing", [*IMP, "--out", "{run_existing}"], "run.mcap"))
    c.append(("import --out missing folder", [*IMP, "--out", "{noparent}/r.mcap"], "--out"))
    c.append(("import --out folder", [*IMP, "--out", "{dir}"], "--out"))
    # ---- survey and its sub-commands
    for flag, values in (("--cameras", ("0", "-1", "1000000000000")), ("--trials", ("0", "1", "-1", "100000000")),
                         ("--sigma-px", ("-1", "nan", "inf")), ("--sigma-2d", ("nan",)), ("--sigma-3d", ("-1", "nan", "1,2")), ("--pixel-pitch-um", ("0", "-1", "nan", "inf")),
                         ("--batch-size", ("0", "-1")), ("--workers", ("-1",)), ("--seed", ("-1",))):
        c += _numeric(SUR, flag, values)
    c.append(("survey --strategies bogus", [*SUR, "--strategies", "bogus"], "bogus"))
    c.append(("survey --model bogus", [*SUR, "--model", "bogus"], "bogus"))
    c.append(("survey --out file", [*SUR, "--out", "{out_file}"], "--out"))
    c.append(("survey --out missing parent", [*SUR, "--out", "{noparent}/r.parquet"], "--out"))
    c.append(("survey --scheduler malformed", [*SUR[:-2], "--scheduler", "tcp://[bad", "--out", "{root}/s.parquet"], "--scheduler"))
    for kind in FILE_KINDS:
        c.append((f"survey report {kind}", ["survey", "report", "{" + kind + "}", "--report-dir", "{root}/rep"], "{" + kind + "}"))
        c.append((f"survey export {kind}", ["survey", "export", "{" + kind + "}", "--to", "{root}/exp.parquet"], "{" + kind + "}"))
    c.append(("survey report damaged part", ["survey", "report", "{results_bad}", "--report-dir", "{root}/rep"], "part-0.parquet"))
    c.append(("survey report truncated part", ["survey", "report", "{results_cut}", "--report-dir", "{root}/rep"], "results-cut"))
    c.append(("survey export truncated part", ["survey", "export", "{results_cut}", "--to", "{root}/exp.parquet"], "results-cut"))
    c.append(("survey report --fig10-trials 0", ["survey", "report", str(SURVEY_PARQUET), "--fig10-trials", "0", "--report-dir", "{root}/rep"], "--fig10-trials"))
    c.append(("survey report --report-dir file", ["survey", "report", str(SURVEY_PARQUET), "--report-dir", "{out_file}"], "--report-dir"))
    c.append(("survey report no results", ["survey", "report"], "results"))
    c.append(("survey export --to missing folder", ["survey", "export", str(SURVEY_PARQUET), "--to", "{noparent}/x.parquet"], "--to"))
    c.append(("survey export --to folder", ["survey", "export", str(SURVEY_PARQUET), "--to", "{dir}"], "--to"))
    c.append(("survey export --to existing file", ["survey", "export", str(SURVEY_PARQUET), "--to", "{out_file}"], "--to"))
    c.append(("survey export no --to", ["survey", "export", str(SURVEY_PARQUET)], "--to"))
    # ---- sim vehicle
    for url in ("udp:127.0.0.1:99999", "udp:127.0.0.1:-1", "udp:127.0.0.1", "tcp:[bad:1", "bogus:1:2", "udp:256.0.0.1:5000", "udp:127.0.0.1:abc"):
        c.append((f"sim vehicle --listen {url}", ["sim", "vehicle", "--listen", url, "--home", "-35.36,149.16,584", "--duration-s", "1"], url.split(":")[-1] if "99999" in url else "--listen"))
    c.append(("sim vehicle --out bad", ["sim", "vehicle", "--out", "udp:127.0.0.1:99999", "--home", "-35.36,149.16,584", "--duration-s", "1"], "99999"))
    for home in ("1,2", "nan,1,2", "91,0,0", "0,181,0", "a,b,c", "0,0,inf"):
        c.append((f"sim vehicle --home {home}", [*SV[:4], "--home=" + home, "--duration-s", "1"], "--home"))
    for flag, values in (("--speedup", BAD_NUMBERS[:4]), ("--boot-s", ("-1", "nan", "inf")), ("--geoid-separation", ("nan", "inf", "1e300")), ("--geoid-sep", ("nan",)),
                         ("--heading", ("nan", "inf")), ("--wp-speed", ("0", "-1", "nan", "inf")), ("--rtl-alt", ("-1", "nan", "inf")),
                         ("--gps-rate-ms", ("0", "-1", "nan", "inf")), ("--max-items", ("0", "-1", "1000000000")),
                         ("--duration-s", ("0", "-1", "nan", "inf")), ("--duration", ("-1",)), ("--seed", ("-1",))):
        c += _numeric(SV, flag, values)
    c.append(("sim vehicle no address", ["sim", "vehicle", "--home", "-35.36,149.16,584"], "--listen"))
    # ---- sim camera
    for kind in FILE_KINDS:
        c.append((f"sim camera --camera {kind}", ["sim", "camera", "--connect", "udpin:127.0.0.1:0", "--camera", "{" + kind + "}",
                                                  "--serve", "http://127.0.0.1:0/s.mjpg", "--duration-s", "1"], "{" + kind + "}"))
    for cam in ("cam_focal0", "cam_negfocal", "cam_nan", "cam_rot", "cam_size0"):
        c.append((f"sim camera --camera {cam}", ["sim", "camera", "--connect", "udpin:127.0.0.1:0", "--camera", "{" + cam + "}",
                                                 "--serve", "http://127.0.0.1:0/s.mjpg", "--duration-s", "1"], "{" + cam + "}"))
    for flag, values in (("--fps", BAD_NUMBERS), ("--latency-s", ("-1", "nan", "inf")), ("--noise-dn", ("-1", "nan", "inf")), ("--noise-px", ("-1",)),
                         ("--jpeg-quality", ("-1", "101")), ("--marker-id", ("-1", "999")), ("--marker-size", ("0", "-1", "nan", "inf")),
                         ("--marker-offset", ("nan,0,0", "1,2")), ("--duration-s", ("-1", "nan")), ("--vehicle-sysid", ("0", "-1", "256"))):
        c += _numeric(SC, flag, values)
    c.append(("sim camera --marker-dictionary bogus", [*SC, "--marker-dictionary", "DICT_BOGUS"], "--marker-dictionary"))
    for flag, values in (("--site-lat", ("nan", "91")), ("--site-lon", ("inf", "181")), ("--site-h", ("nan",)), ("--site-mount-height", ("0", "-1", "nan")),
                         ("--site-tilt", ("nan", "inf")), ("--site-focal-px", ("0", "-1", "nan", "inf")), ("--site-image-size", ("0x0", "-1x5", "axb")),
                         ("--site-distortion", ("nan,0,0,0,0", "1,2"))):
        c += _numeric(SCS, flag, values)
    c.append(("sim camera --write-truth missing folder", [*SCS, "--write-truth", "{noparent}/truth.yaml"], "--write-truth"))
    c.append(("sim camera --write-truth folder", [*SCS, "--write-truth", "{dir}"], "--write-truth"))
    c.append(("sim camera --write-truth read-only", [*SCS, "--write-truth", "{ro}.yaml"], "--write-truth"))
    for url in ("bogus", "udpin:127.0.0.1:99999", "udpin:[bad:1"):
        c.append((f"sim camera --connect {url}", ["sim", "camera", "--connect", url, *SC[4:]], url))
    for url in ("ftp://127.0.0.1:0/s.mjpg", "http://[bad/s.mjpg", "http://127.0.0.1:99999/s.mjpg"):
        c.append((f"sim camera --serve {url}", [*SC[:6], "--serve", url, "--duration-s", "1"], "--serve"))
    # ---- plan (the site file and flags are checked before any design work)
    for kind in FILE_KINDS:
        c.append((f"plan --site {kind}", ["plan", "--site", "{" + kind + "}", "--out", "{root}/plan-out"], "--lat" if kind == "empty" else "{" + kind + "}"))
    for flag, values in (("--mount-height", ("0", "-1", "nan", "inf")), ("--focal-px", ("0", "-1", "nan", "inf")), ("--hfov", ("0", "-1", "180", "nan")),
                         ("--fps", ("0", "-1", "nan")), ("--exposure-s", ("-1", "nan")), ("--marker-size", ("0", "-1", "nan")),
                         ("--marker-id", ("-1", "999")), ("--marker-offset", ("nan,0,0", "1,2")), ("--min-marker-px", ("0", "-1")),
                         ("--min-agl", ("-1", "nan")), ("--keep-out", ("-1", "nan")), ("--speed", ("0", "-1", "nan", "inf")),
                         ("--hover", ("-1", "nan")), ("--endurance", ("0", "-1", "nan")), ("--gnss-hz", ("0", "-1")),
                         ("--trials", ("0", "1", "-1")), ("--sigma-px", ("-1", "nan")), ("--lat", ("91", "nan")), ("--lon", ("181",)),
                         ("--image-size", ("0x0", "10x10", "axb"))):
        c += _numeric(PLAN, flag, values)
    c.append(("plan --marker-dictionary bogus", [*PLAN, "--marker-dictionary", "DICT_BOGUS"], "DICT_BOGUS"))
    c.append(("plan --aruco-dict bogus (old name)", [*PLAN, "--aruco-dict", "DICT_BOGUS"], "DICT_BOGUS"))
    c.append(("plan --out file", ["plan", "--site", "{site}", "--out", "{out_file}"], "--out"))
    c.append(("plan --out missing parent", ["plan", "--site", "{site}", "--out", "{noparent}/deeper"], "--out"))
    c.append(("plan --out read-only", ["plan", "--site", "{site}", "--out", "{ro}"], "--out"))
    c.append(("plan --roi missing", [*PLAN, "--roi", "{missing}"], "{missing}"))
    c.append(("plan --roi garbage", [*PLAN, "--roi", "{garbage}"], "{garbage}"))
    c.append(("plan --roi binary", [*PLAN, "--roi", "{binary}"], "{binary}"))
    c.append(("plan --scheduler malformed", [*PLAN, "--strategy", "paper-far", "--scheduler", "tcp://[bad"], "--scheduler"))
    # ---- demo (refused before the simulators start)
    c += _numeric(DEMO, "--speedup", ("0", "-1", "nan", "inf", "1000"))
    c += _numeric(DEMO, "--trials", ("1", "-1", "1000000"))
    c.append(("demo --out file", ["demo", "--out", "{out_file}"], "--out"))
    c.append(("demo --out missing parent", ["demo", "--out", "{noparent}/deeper"], "--out"))
    c.append(("demo --out read-only", ["demo", "--out", "{ro}"], "--out"))
    # ---- argparse itself: one line too
    c.append(("plan --sigma-px abc", [*PLAN, "--sigma-px", "abc"], "abc"))
    c.append(("calibrate --trials abc", [*CAL, "--trials", "abc"], "abc"))
    c.append(("survey report --bogus", ["survey", "report", str(SURVEY_PARQUET), "--bogus"], "--bogus"))
    c.append(("unknown command", ["flyy"], "flyy"))
    return c


CASES = _cases()


def _run(argv: list[str]) -> tuple[object, str, str]:
    """(exit code or 'traceback', stdout, stderr) of one in-process run."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code: object = main(argv)
        except SystemExit as exc:
            code = exc.code
        except Exception:  # noqa: BLE001 - the point of the table: report it as a traceback
            traceback.print_exc(file=err)
            code = "traceback"
    return code, out.getvalue(), err.getvalue()


@pytest.mark.timeout(CASE_TIMEOUT_S)
@pytest.mark.parametrize("case_id, argv, needle", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2(files: dict[str, str], case_id: str, argv: list[str], needle: str) -> None:
    argv = [a.format_map(files) for a in argv]
    needle = needle.format_map(files)
    before = _snapshot(files["root"])
    code, _out, err = _run(argv)
    assert "Traceback" not in err, f"{case_id}: traceback\n{err}"
    assert code == 2, f"{case_id}: exit {code}\n{err}"
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"{case_id}: {len(lines)} lines on stderr\n{err}"
    assert needle.lower() in lines[0].lower() or Path(needle).name.lower() in lines[0].lower(), f"{case_id}: the line does not name {needle!r}: {lines[0]}"
    after = _snapshot(files["root"])
    changed = {k for k in before if before[k] != after.get(k)}
    assert not changed, f"{case_id}: changed or removed {sorted(changed)}"
    assert set(after) == set(before), f"{case_id}: left {sorted(set(after) - set(before))}"


def test_the_table_covers_every_command() -> None:
    per_command: dict[str, int] = {}
    for _id, argv, _needle in CASES:
        key = " ".join(argv[:2]) if argv[0] in ("sim",) or (argv[0] == "survey" and argv[1] in ("report", "export")) else argv[0]
        per_command[key] = per_command.get(key, 0) + 1
    for command in ("plan", "fly", "calibrate", "uncertainty", "import", "survey", "survey report", "survey export", "sim vehicle", "sim camera", "demo"):
        assert per_command.get(command, 0) >= 5, (command, per_command)
    assert len(CASES) >= 200


def _subparser(parser, *names: str):
    for name in names:
        action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        parser = action.choices[name]
    return parser


def test_one_vocabulary_across_commands() -> None:
    """The same thing has the same flag, unit and default everywhere; old names parse but are not listed."""
    from dronecal_field.cli import build_parser

    root = build_parser()
    parsers = {name: _subparser(root, *name.split()) for name in ("plan", "fly", "import", "sim camera", "sim vehicle", "uncertainty", "survey")}
    options = {name: {s: a for a in p._actions for s in a.option_strings} for name, p in parsers.items()}
    for name in ("plan", "fly", "import", "sim camera"):
        for flag in ("--marker-dictionary", "--marker-id", "--marker-size", "--marker-offset"):
            assert flag in options[name] and options[name][flag].help != "==SUPPRESS==", (name, flag)
        assert options[name]["--marker-offset"].metavar == "F,R,D", name
    assert options["import"]["--marker-offset"].default == options["sim camera"]["--marker-offset"].default == "0,0,0"
    assert options["sim camera"]["--marker-size"].default == 0.3
    for name in ("uncertainty", "survey"):
        assert options[name]["--sigma-px"].default == 2.0
    assert "--duration-s" in options["sim vehicle"] and "--duration-s" in options["sim camera"]
    assert "--geoid-separation" in options["sim vehicle"] and "--geoid-separation" in options["plan"]
    hidden = {"plan": "--aruco-dict", "sim vehicle": ("--duration", "--geoid-sep"), "uncertainty": "--sigma-2d", "survey": "--sigma-2d", "sim camera": "--noise-px"}
    for name, flags in hidden.items():
        help_text = parsers[name].format_help()
        for flag in (flags,) if isinstance(flags, str) else flags:
            assert options[name][flag].help == "==SUPPRESS==" and f"{flag} " not in help_text, (name, flag)
    # an old name lands where the new one does
    args = root.parse_args(["sim", "vehicle", "--home", "0,0,0", "--duration", "3", "--geoid-sep", "1.5"])
    assert (args.duration, args.geoid_sep) == (3.0, 1.5)
    args = root.parse_args(["plan", "--out", "x", "--aruco-dict", "DICT_5X5_50"])
    assert args.aruco_dict == "DICT_5X5_50"
