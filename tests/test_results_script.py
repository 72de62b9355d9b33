"""benchmarks/results.py rewrites docs/RESULTS.md's generated blocks and nothing else: on tiny
runs in the shape the benchmarks print (no clips, no peers, no benchmark run)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
results = pytest.importorskip("results")

PROSE_BEFORE = "# Results\n\nSome prose, r 0.123 by hand.\n\n"
PROSE_AFTER = "\nMore prose after: 4 of 5 clips.\n"


def page(*names: str, inside: str = "old table\n") -> str:
    middle = "\n".join(f"<!-- results:{n} begin -->\n{inside}<!-- results:{n} end -->\n"
                       for n in names)
    return PROSE_BEFORE + middle + PROSE_AFTER


def peers_run(r: float = 0.951) -> dict:
    """One clip in ``benchmarks/peers.py --json``'s shape, with the fields corpus_summary
    reads."""
    gap = {"gap": 0.012, "ci95": [0.004, 0.02], "peer": "facemesh_v1"}
    return {"load_average": {"start": [1.5, 2.0, 2.5], "end": [1.0, 1.25, 3.0]},
            "command": "benchmarks/peers.py --json --methods articast", "variant": "fused",
            "offline": False,
            "clips": [{"clip": "franck", "held_out_frames": 100,
                       "load_average_at_start": [1.5, 2.0, 2.5],
                       "methods": {
                           "articast": {"judge_r": r, "ok": 1.0, "occluded_frames": [3, 4],
                                        "jitter_pct_width": 0.2,
                                        "judge_lag_velocity_frames": 0, "consensus_r": 0.97,
                                        "truth_r": None},
                           "facemesh_v1": {"judge_r": 0.939, "jitter_pct_width": 0.25},
                           "dlib": {"judge_r": 0.944}},
                       "articast_vs_reader": {"r_vs_reader": gap, "r_vs_best_facemesh": gap,
                                              "lag_velocity_vs_reader": 0}}]}


def run(tmp_path: Path, *args: str) -> int:
    return results.main(["--run-dir", str(tmp_path / "RUN"), "--results",
                         str(tmp_path / "RESULTS.md"), "--plots", str(tmp_path / "plots"),
                         *args])


@pytest.fixture
def stored(tmp_path: Path) -> Path:
    (tmp_path / "RUN").mkdir()
    (tmp_path / "RUN/live.json").write_text(json.dumps(peers_run()))
    (tmp_path / "RUN/live.meta.json").write_text(json.dumps({
        "command": f"benchmarks/peers.py --json --others {tmp_path / 'RUN'}/series",
        "date_start": "2026-11-29 10:00 UTC", "date_end": "2026-11-29 10:20 UTC",
        "commit": "abc1234", "load_start": [1.5, 2.0, 2.5], "load_end": [1.0, 1.25, 3.0]}))
    (tmp_path / "RESULTS.md").write_text(page("live", "offline"))
    return tmp_path


def test_from_stored_rewrites_only_between_the_markers_and_again_the_same(stored):
    assert run(stored, "--from-stored", "--only", "live", "--no-plots") == 0
    text = (stored / "RESULTS.md").read_text()
    assert text.startswith(PROSE_BEFORE) and text.endswith(PROSE_AFTER)
    begin, end = text.index("<!-- results:live begin -->"), text.index(
        "<!-- results:live end -->")
    block = text[begin:end]
    assert "old table" not in block
    assert "| franck |" in block and "| 0.951 | 0.939 |" in block
    assert "+0.012 (+0.004..+0.020) better" in block
    # the line under the heading: command (the run folder shown as RUN), date, commit, load
    assert "ran `benchmarks/peers.py --json --others RUN/series`" in block
    assert "2026-11-29 10:00 UTC to 2026-11-29 10:20 UTC" in block
    assert "commit abc1234" in block and "1.5 2 2.5 at start, 1 1.25 3 at end" in block
    # a section not asked for keeps its old table
    assert "<!-- results:offline begin -->\nold table\n<!-- results:offline end -->" in text
    assert run(stored, "--from-stored", "--only", "live", "--no-plots") == 0
    assert (stored / "RESULTS.md").read_text() == text  # idempotent
    # a changed run changes the table
    (stored / "RUN/live.json").write_text(json.dumps(peers_run(0.9)))
    assert run(stored, "--from-stored", "--only", "live", "--no-plots") == 0
    assert "| 0.900 | 0.939 |" in (stored / "RESULTS.md").read_text()


def test_the_old_names_of_issue_38_runs_are_read(tmp_path):
    (tmp_path / "RUN").mkdir()
    (tmp_path / "RUN/final5.json").write_text(json.dumps(peers_run()))
    (tmp_path / "RESULTS.md").write_text(page("live"))
    assert run(tmp_path, "--from-stored", "--only", "live", "--no-plots") == 0
    text = (tmp_path / "RESULTS.md").read_text()
    assert "### RUN/final5.json" in text and "| franck |" in text
    # no meta file: the command and load from the JSON, the date from the file
    assert "commit not recorded" in text and "the file's time" in text
    assert "1.5 2 2.5 at start" in text


@pytest.mark.parametrize("bad", [
    PROSE_BEFORE + "<!-- results:live begin -->\nx\n" + PROSE_AFTER,
    PROSE_BEFORE + "x\n<!-- results:live end -->\n" + PROSE_AFTER,
    page("live") + "<!-- results:live begin -->\n<!-- results:live end -->\n",
    PROSE_BEFORE + "<!-- results:live begin -->\n<!-- results:offline begin -->\n"
    "<!-- results:offline end -->\n<!-- results:live end -->\n",
])
def test_a_page_whose_markers_do_not_pair_up_is_refused_unchanged(stored, bad, capsys):
    (stored / "RESULTS.md").write_text(bad)
    assert run(stored, "--from-stored", "--no-plots") == 2
    assert (stored / "RESULTS.md").read_text() == bad
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "markers do not pair up" in err[0]


def test_a_run_folder_with_none_of_the_runs_writes_nothing(tmp_path, capsys):
    (tmp_path / "RUN").mkdir()
    (tmp_path / "RESULTS.md").write_text(page("live"))
    assert run(tmp_path, "--from-stored", "--no-plots") == 2
    assert (tmp_path / "RESULTS.md").read_text() == page("live")
    assert "none of the stored runs" in capsys.readouterr().err


def test_a_section_without_its_inputs_is_skipped_with_the_reason_in_its_block(tmp_path,
                                                                              capsys):
    (tmp_path / "RESULTS.md").write_text(page("live"))
    (tmp_path / "empty").mkdir()
    assert run(tmp_path, "--only", "live", "--clips", str(tmp_path / "empty")) == 0
    text = (tmp_path / "RESULTS.md").read_text()
    assert f"**skipped**: no clips in {tmp_path / 'empty'}" in text
    assert "*not run `benchmarks/peers.py --json --clips" in text
    assert text.startswith(PROSE_BEFORE) and text.endswith(PROSE_AFTER)
    assert not (tmp_path / "RUN/live.json").exists()
    meta = json.loads((tmp_path / "RUN/live.meta.json").read_text())
    assert meta["skipped"].startswith("no clips") and len(meta["load_start"]) == 3
    err = capsys.readouterr().err
    assert "live: skipped: no clips" in err and "Traceback" not in err


def fake(code: str):
    """A spawn that runs ``code`` instead of the benchmark."""
    def spawn(argv, **kw):
        return subprocess.Popen([sys.executable, "-c", code], **kw)
    return spawn


def test_a_run_keeps_its_output_and_its_date_commit_and_load(tmp_path):
    run_dir = tmp_path / "RUN"
    run_dir.mkdir()
    section = results.BY_NAME["upper_synthetic"]
    code = ("import json, sys; print('step 1', file=sys.stderr); "
            "print(json.dumps({'blink_f1': 1.0, 'gaze': {'median_deg': 1.33}}))")
    results.execute(section, run_dir, tmp_path, tmp_path, spawn=fake(code))
    assert json.loads((run_dir / "upper_synthetic.json").read_text())["blink_f1"] == 1.0
    assert (run_dir / "upper_synthetic.log").read_text() == "step 1\n"
    meta = json.loads((run_dir / "upper_synthetic.meta.json").read_text())
    assert meta["command"].startswith("benchmarks/upper_synthetic.py --seconds 60 --json")
    assert meta["date_start"].endswith("UTC") and len(meta["load_end"]) == 3
    assert "skipped" not in meta
    text = results.block(section, run_dir, None, tmp_path / "RESULTS.md")
    assert "| gaze.median_deg | 1.33 |" in text and "| blink_f1 | 1 |" in text
    # a failing benchmark: skipped with its last line, the earlier output set aside
    results.execute(section, run_dir, tmp_path, tmp_path,
                    spawn=fake("import sys; sys.exit('no renderer here')"))
    assert not (run_dir / "upper_synthetic.json").exists()
    assert (run_dir / "upper_synthetic.previous.json").exists()
    text = results.block(section, run_dir, None, tmp_path / "RESULTS.md")
    assert "**skipped**: benchmarks/upper_synthetic.py failed (exit 1): no renderer here" \
        in text


def test_docs_results_has_one_block_per_section_and_no_other():
    names = results.blocks(results.RESULTS.read_text())
    assert set(names) == set(results.BY_NAME)


def test_plots_are_drawn_from_the_numbers(stored):
    pytest.importorskip("matplotlib")
    assert run(stored, "--from-stored", "--only", "live") == 0
    assert (stored / "plots/live.png").stat().st_size > 1000
    assert "![lip aperture r per clip" in (stored / "RESULTS.md").read_text()


def test_a_stored_run_that_cannot_be_read_leaves_its_block_and_says_so(stored, capsys):
    (stored / "RUN/live.json").write_text('{"clips": [{"no": "methods"}]}')
    assert run(stored, "--from-stored", "--only", "live", "offline", "--no-plots") == 1
    text = (stored / "RESULTS.md").read_text()
    assert "<!-- results:live begin -->\nold table\n<!-- results:live end -->" in text
    # offline, with no stored run in RUN: its block is kept too (a RUN folder may hold some
    # sections only; their tables stand as an earlier RUN wrote them)
    assert "<!-- results:offline begin -->\nold table\n<!-- results:offline end -->" in text
    assert "*no stored run yet" not in text
    err = capsys.readouterr().err
    assert "live: " in err and "cannot be tabulated (KeyError" in err
    assert "offline: no stored run" in err
    assert "Traceback" not in err


def test_json_lines_and_text_outputs_are_shown_as_printed(tmp_path):
    out = tmp_path / "latency.json"
    out.write_text('{"subscribers": 1, "p50_ms": 0.66}\n{"subscribers": 100, "p50_ms": 2.5}\n')
    data = results.read_output(out, "json")
    assert data == [{"subscribers": 1, "p50_ms": 0.66}, {"subscribers": 100, "p50_ms": 2.5}]
    table = results.json_table(data)
    assert "| key | 1 | 100 |" in table and "| p50_ms | 0.66 | 2.5 |" in table
    assert results.text_table("la_lin 3.2 ms\n\n") == "```text\nla_lin 3.2 ms\n```"


def test_the_synthetic_speakers_evaluation_is_a_row_per_condition_and_model(tmp_path):
    """``articast evaluate --json`` (conditions -> models -> figures) as one row each, not a
    key per figure (585 rows before)."""
    (tmp_path / "RUN").mkdir()
    figures = {"rms_mm_mean": 0.444112, "rms_mm_median": 0.37961, "rms_mm_p95": 1.05995,
               "ok_fraction": 1.0, "evals_per_frame": 8.01333, "ms_per_frame": 4.9,
               "jitter_mm": 0.0306389, "lag_frames": 0.0}
    (tmp_path / "RUN/evaluate.json").write_text(json.dumps({"conditions": {
        "teleconference": {"la_lin": figures},
        "postures": {"la_lin": {**figures, "jitter_mm": None, "lag_frames": None}}}}))
    (tmp_path / "RESULTS.md").write_text(page("evaluate"))
    assert run(tmp_path, "--from-stored", "--only", "evaluate", "--no-plots") == 0
    text = (tmp_path / "RESULTS.md").read_text()
    assert "| teleconference | la_lin | 0.444 | 0.38 | 1.06 | 1 | 8.01 | 4.9 | 0.0306 | 0 |" \
        in text, text
    assert "| postures | la_lin | 0.444 | 0.38 | 1.06 | 1 | 8.01 | 4.9 | – | – |" in text
    assert "conditions.teleconference" not in text


def test_the_goal_is_scored_against_the_best_single_peer_not_each_clips_best():
    """Issue 38's goal names *the best single peer*: the one FaceMesh-family method with the
    best mean r over the clips, not each clip's best (a stricter, different bar). Two people:
    v2 is best pooled though v1 is best on one clip; the gap is articast's minus v2's."""
    import corpus_summary as cs

    def clip(name, a, v1, v2, mp):
        return {"clip": name, "held_out_frames": 100, "methods": {
            "articast": {"judge_r": a}, "facemesh_v1": {"judge_r": v1},
            "facelandmarker_v2": {"judge_r": v2}, "mediapipe": {"judge_r": mp},
            "dlib": {"judge_r": 0.99}}}

    clips = [clip("franck", 0.95, 0.96, 0.93, 0.955), clip("cap13", 0.90, 0.80, 0.92, 0.81)]
    rows = [cs.clip_row(c) for c in clips]
    got = cs.single_peer(rows, clips)
    assert got["peer"] == "facelandmarker_v2" and got["clips"] == 2 and got["people"] == 2
    assert got["mean"] == pytest.approx(((0.95 - 0.93) + (0.90 - 0.92)) / 2, abs=1e-4)
    lo, hi = got["ci95"]
    assert lo == pytest.approx(-0.02, abs=1e-4) and hi == pytest.approx(0.02, abs=1e-4)
    line = cs.markdown({"command": "x"}, rows, cs.pools_of(rows, clips)).splitlines()[-1]
    assert line.startswith("pooled all, to the best single peer (facelandmarker_v2")
    assert line.endswith("not worse")
