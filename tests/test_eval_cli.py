"""rs-eval, rs-render and rs-export on a short real rainyscape-nerf run of the tiny scene."""

from __future__ import annotations

import io
import json
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import pytest

from test_report import chromium_probe, html_references

ITERS = 8  # 4 warm-up steps, then 4 joint steps with the rain head: every output exists


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, tiny_scene_dir) -> Path:
    from rainyscape.config import method_config
    from rainyscape.workflow import train_and_evaluate

    out = tmp_path_factory.mktemp("eval_cli")
    cfg = method_config("rainyscape-nerf", [f"data={tiny_scene_dir}", f"trainer.max_iters={ITERS}",
                                            f"trainer.output_dir={out}", "trainer.device=cpu",
                                            "trainer.progress=false", "trainer.eval_every=4", "trainer.log_every=1"])
    return train_and_evaluate(cfg).run_dir


@dataclass
class Done:
    returncode: int
    stdout: str
    stderr: str


def _cli(*args: str) -> Done:
    """Run a CLI's main in this process (as its console script does, minus interpreter start-up)."""
    from rainyscape.cli import eval as eval_cli, export as export_cli, render as render_cli, run_cli

    main = {"rs-eval": eval_cli.main, "rs-render": render_cli.main, "rs-export": export_cli.main}[args[0]]
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = run_cli(main, list(args[1:]))
    return Done(code, out.getvalue(), err.getvalue())


def test_rs_eval_writes_every_field_and_a_working_report(trained_run):
    (trained_run / "metrics.json").unlink()
    (trained_run / "report.html").unlink()
    done = _cli("rs-eval", str(trained_run), "device=cpu")
    assert done.returncode == 0, done.stderr
    assert "train_psnr" in done.stdout and "rainy_input_psnr" in done.stdout
    m = json.loads((trained_run / "metrics.json").read_text())
    s = m["summary"]
    for key in ("rainy_input_psnr", "rainy_input_ssim", "train_psnr", "train_ssim",
                "train_rain-mask-fusion_psnr", "train_rain-mask-fusion_ssim", "train_streak-fusion_psnr",
                "train_streak-fusion_random_psnr", "heldout_psnr", "heldout_ssim",
                "train_psnr_vs_rainy", "rain_angle_true_deg"):
        assert isinstance(s[key], float), key
    for key in ("rain_angle_deg", "residual_angle_deg", "rain_correlation"):  # None: no streaks predicted yet
        assert key in s and (s[key] is None or isinstance(s[key], float)), key
    assert s["rainy_input_psnr"] > s["train_psnr"] - 50 and 0 < s["train_ssim"] <= 1
    assert m["step"] == ITERS and m["postprocess"] == ["rain-mask-fusion", "streak-fusion"]
    assert m["lpips"]["available"] or m["lpips"]["reason"]
    assert {r["split"] for r in m["per_view"]} == {"train", "heldout"} and len(m["per_view"]) == 12
    report = trained_run / "report.html"
    refs, _ = html_references(report.read_text())
    assert all(r.startswith("data:image/png;base64,") or (trained_run / r).exists() for r in refs)
    images, broken = chromium_probe(report)
    assert images >= 3 + 3 and broken == 0  # loss / PSNR / diagnostics plots and the strips


def test_rs_render_images_video_and_embedding_study(trained_run):
    import imageio.v2 as imageio

    done = _cli("rs-render", str(trained_run), "views=001,002,heldout", "frames=5", "fps=5", "device=cpu")
    assert done.returncode == 0, done.stderr
    renders = trained_run / "renders"
    assert len(list((renders / "clean").glob("*.png"))) == 3
    assert len(list((renders / "rain").glob("*.png"))) == 2  # training views only
    assert len(list((renders / "error").glob("*.png"))) == 3 and len(list((renders / "depth").glob("*.npy"))) == 3
    strip = imageio.imread(renders / "strips" / "001.png")
    assert strip.shape[1] > 4 * strip.shape[0] * 0.8  # rainy | render | fused | truth | rain | true rain
    reader = imageio.get_reader(renders / "path.mp4")
    assert reader.count_frames() >= 5
    reader.close()
    study = _cli("rs-render", str(trained_run), "--embedding-study", "patch=24", "device=cpu")
    assert study.returncode == 0, study.stderr
    stats = json.loads((renders / "embedding_study.json").read_text())
    assert [s["embedding"] for s in stats[:4]] == ["learnt", "s + noise", "v + noise", "p + noise"]
    assert (renders / "embedding_study.png").is_file()
    assert "Embedding study" in (trained_run / "report.html").read_text()


def test_rs_export_cameras(trained_run):
    out = trained_run / "exported"
    done = _cli("rs-export", str(trained_run), "what=cameras", f"out={out}", "device=cpu")
    assert done.returncode == 0, done.stderr
    content = json.loads((out / "transforms.json").read_text())
    assert len(content["frames"]) == 12 and content["w"] == 48
    assert all((out / f["file_path"]).is_file() for f in content["frames"])


def test_rs_export_never_overwrites_a_folder_of_yours(tmp_path, trained_run):
    scene = tmp_path / "scene"  # what rs-process-data writes: the user's own dataset
    (scene / "images").mkdir(parents=True)
    files = {scene / "transforms.json": b'{"frames": ["mine"]}',
             scene / "images" / "001.png": bytes(range(256)) * 4, scene / "notes.txt": b"keep me\n"}
    for path, content in files.items():
        path.write_bytes(content)
    done = _cli("rs-export", str(trained_run), "what=cameras", f"out={scene}", "device=cpu")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert done.stderr.startswith("error: ") and str(scene) in done.stderr and "force=true" in done.stderr
    assert {p: p.read_bytes() for p in files} == files  # byte for byte
    assert sorted(p.name for p in scene.rglob("*")) == ["001.png", "images", "notes.txt", "transforms.json"]
    forced = _cli("rs-export", str(trained_run), "what=cameras", f"out={scene}", "device=cpu", "force=true")
    assert forced.returncode == 0, forced.stderr
    assert len(json.loads((scene / "transforms.json").read_text())["frames"]) == 12
    assert (scene / "notes.txt").read_bytes() == files[scene / "notes.txt"]  # only its own files replaced


def test_cli_errors_are_one_line(tmp_path, trained_run):
    for args in (["rs-eval", str(tmp_path)], ["rs-render", str(tmp_path)], ["rs-export", str(tmp_path)],
                 ["rs-eval"], ["rs-export", str(trained_run), "what=everything"],
                 ["rs-render", str(trained_run), "views=nope"], ["rs-eval", str(trained_run), "stepp=3"]):
        done = _cli(*args)
        assert done.returncode == 2, args
        assert done.stderr.startswith("error: ") and "Traceback" not in done.stderr, done.stderr
    # the installed console script behaves the same
    script = subprocess.run(["rs-eval", str(tmp_path)], capture_output=True, text=True)
    assert script.returncode == 2 and script.stderr.startswith("error: ") and str(tmp_path) in script.stderr


def test_rs_eval_changes_post_processes_only(trained_run):
    """A finished run is evaluated under other post-processes than it trained with; every
    other override is refused (the checkpoint fixes it), naming the key."""
    done = _cli("rs-eval", str(trained_run), "device=cpu", "postprocess.streak-fusion=none")
    assert done.returncode == 0, done.stderr
    m = json.loads((trained_run / "metrics.json").read_text())
    assert m["postprocess"] == ["rain-mask-fusion"]
    assert "train_rain-mask-fusion_psnr" in m["summary"] and "train_streak-fusion_psnr" not in m["summary"]
    bad = _cli("rs-eval", str(trained_run), "device=cpu", "field.hidden=8")
    assert bad.returncode == 2 and "field.hidden=8" in bad.stderr and "postprocess" in bad.stderr
    assert _cli("rs-eval", str(trained_run), "device=cpu").returncode == 0  # as trained, for the next tests
    m = json.loads((trained_run / "metrics.json").read_text())
    assert m["postprocess"] == ["rain-mask-fusion", "streak-fusion"]
