"""RunFolder owns a run folder's layout and its questions: no other module spells status.json,
run.lock or the checkpoints folder, and "finished" is decided in one place that rs-train
and rs-bench both ask."""

from __future__ import annotations

import ast
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from rainyscape.engine.checkpoint import save_checkpoint
from rainyscape.engine.run_folder import RunFolder, reached_end
from rainyscape.errors import ConfigError, RainyScapeError

ROOT = Path(__file__).resolve().parents[1] / "rainyscape"
HOME = ROOT / "engine" / "run_folder.py"
# torch hub keeps downloaded weights in its own "checkpoints" folder (not a run's)
NOT_A_RUN = {("eval/perceptual.py", "checkpoints")}


def _spellings(path: Path) -> list[tuple[int, str]]:
    """String constants of ``path`` (docstrings aside) naming a run folder's status file,
    lock file or checkpoints folder."""
    tree = ast.parse(path.read_text())
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs:
            for name in ("status.json", "run.lock", "checkpoints"):
                if name in n.value:
                    out.append((n.lineno, name))
    return out


def test_no_module_but_run_folder_names_its_files():
    assert {name for _, name in _spellings(HOME)} == {"status.json", "run.lock", "checkpoints"}
    found = [f"{p.relative_to(ROOT)}:{line}: {name}" for p in sorted(ROOT.rglob("*.py")) if p != HOME
             for line, name in _spellings(p) if (str(p.relative_to(ROOT)), name) not in NOT_A_RUN]
    assert not found, "ask RunFolder (rainyscape/engine/run_folder.py):\n" + "\n".join(found)


def _reads_state(node: ast.AST) -> bool:
    """``x.get("state")`` or ``x["state"]``."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
        return bool(node.args) and isinstance(node.args[0], ast.Constant) and node.args[0].value == "state"
    return isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and node.slice.value == "state"


def test_finished_is_decided_by_run_folder_alone():
    deciders = []
    for p in sorted(ROOT.rglob("*.py")):
        for n in ast.walk(ast.parse(p.read_text())):
            if isinstance(n, ast.Compare):
                sides = [n.left, *n.comparators]
                if any(_reads_state(s) for s in sides) and any(
                        isinstance(s, ast.Constant) and s.value == "finished" for s in sides):
                    deciders.append(f"{p.relative_to(ROOT)}:{n.lineno}")
    assert len(deciders) == 1 and deciders[0].startswith("engine/run_folder.py:"), deciders  # RunFolder.finished
    for asker in ("comparison/cell.py", "cli/train.py"):
        calls = [n for n in ast.walk(ast.parse((ROOT / asker).read_text()))
                 if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "finished"]
        assert calls, f"{asker} must ask RunFolder.finished"


def test_layout_and_is_a_run(tmp_path):
    folder = RunFolder(tmp_path)
    assert not RunFolder.is_run(tmp_path)
    with pytest.raises(ConfigError, match="not a run folder"):
        RunFolder.check(tmp_path)
    folder.config_file.write_text("method: x\n")
    assert RunFolder.check(tmp_path).path == tmp_path
    names = {p.relative_to(tmp_path).as_posix() for p in (folder.config_file, folder.status_file, folder.checkpoints,
                                                           folder.log_file, folder.metrics_file, folder.renders,
                                                           folder.report_file, folder.strips)}
    assert names == {"config.yml", "status.json", "checkpoints", "log.jsonl", "metrics.json", "renders",
                     "report.html", "renders/strips"}
    assert folder.lock().path == tmp_path / "run.lock"


def test_a_running_status_without_its_process_reads_interrupted(tmp_path):
    folder = RunFolder(tmp_path)
    assert folder.status() == {}
    folder.set_status("running")
    with folder.lock():
        assert folder.status()["state"] == "running"  # the owner holds the lock
    status = folder.status()
    assert status["state"] == "interrupted" and "resume" in status["note"]
    assert json.loads(folder.status_file.read_text())["state"] == "interrupted"  # corrected on disk too


def test_finished_needs_the_status_the_metrics_and_every_step(tmp_path):
    folder = RunFolder(tmp_path)
    folder.set_status("finished", step=40)
    assert not folder.finished(40)  # evaluation not written yet
    folder.save_metrics({"summary": {}})
    assert folder.finished(40) and not folder.finished(50)  # a longer run may continue
    assert reached_end(40, 40) and not reached_end(39, 40)
    assert not folder.resumable(50)  # ... once it has a checkpoint
    save_checkpoint(folder.checkpoints, 40, {"step": 40, "models": {}, "optimizers": {}, "rng": {}}, keep=2)
    assert folder.resumable(50) and not folder.resumable(40)


def test_which_checkpoint_is_restored_and_one_error_for_a_misfit(tmp_path):
    folder = RunFolder(tmp_path)
    with pytest.raises(RainyScapeError, match="no checkpoint found"):
        folder.checkpoint_to_restore("cpu")
    small = nn.Linear(2, 2)
    for step in (10, 20):
        save_checkpoint(folder.checkpoints, step, {"step": step, "models": {"field": small.state_dict()},
                                                   "optimizers": {}, "rng": {}}, keep=5)
    (folder.checkpoints / "step-0000030.pt").write_bytes(b"torn")  # a newer one that does not read
    path, state = folder.checkpoint_to_restore("cpu")
    assert path.name == "step-0000020.pt" and state["step"] == 20  # the newest that reads
    assert folder.checkpoint_to_restore("cpu", step=10)[1]["step"] == 10  # or the one named
    with pytest.raises(RainyScapeError, match="no checkpoint of step 15"):
        folder.checkpoint_to_restore("cpu", step=15)
    pipeline = SimpleNamespace(device=torch.device("cpu"), models=lambda: {"field": nn.Linear(2, 2)})
    assert folder.restore(pipeline) == 20
    wrong = SimpleNamespace(device=torch.device("cpu"), models=lambda: {"field": nn.Linear(3, 2)})
    with pytest.raises(RainyScapeError, match=r"step-0000020.pt: does not fit this run's config \(RuntimeError"):
        folder.restore(wrong)


def test_log_records_skip_a_torn_line_and_cut_drops_later_steps(tmp_path):
    folder = RunFolder(tmp_path)
    for step in (1, 2, 3):
        folder.append_log({"step": step, "loss": 1.0 / step})
    with open(folder.log_file, "a") as fh:
        fh.write('{"step": 4, "lo')
    assert [r["step"] for r in folder.log_records()] == [1, 2, 3]
    folder.cut_log(2)
    assert [r["step"] for r in folder.log_records()] == [1, 2]
    assert folder.log_file.read_text().endswith("\n")


def test_runs_under_an_output_folder(tmp_path):
    for stamp in ("2024-01-01_000000", "2024-01-02_000000"):
        (tmp_path / "scene" / "nerf" / stamp).mkdir(parents=True)
        RunFolder(tmp_path / "scene" / "nerf" / stamp).config_file.write_text("method: nerf\n")
    (tmp_path / "scene" / "nerf" / "not-a-run").mkdir()
    assert [r.path.name for r in RunFolder.under(tmp_path)] == ["2024-01-01_000000", "2024-01-02_000000"]
