import io

import pytest

from nrsfm import solve
from nrsfm.cli import main
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.progress import Progress, ProgressBars, listen, report


def test_reports_reach_the_listener_only_inside_listen():
    seen: list[Progress] = []
    report("x", "stage", 1)  # nobody listens: nothing happens
    with listen(seen.append):
        report("x", "stage", 2, 10, cost=1.5)
    report("x", "stage", 3)
    assert seen == [Progress("x", "stage", 2, 10, {"cost": 1.5})]


@pytest.mark.parametrize("name, stage, missing", [("csf2", "shape", 0.0), ("csf2", "camera rounds", 0.2),
                                                  ("pr", "L-BFGS", 0.0), ("spm", "shape ADMM", 0.0),
                                                  ("empnd", "EM", 0.0), ("emppca", "EM", 0.0)])
def test_every_iterative_solver_reports_its_iterations(name, stage, missing):
    seq = lowrank_sequence(40, 12, 2, seed=1, noise=1e-3, missing=missing)
    seen: list[Progress] = []
    with listen(seen.append):
        rec = solve(seq, name)
    mine = [p for p in seen if (p.solver, p.stage) == (name, stage)]
    assert mine, {(p.solver, p.stage) for p in seen}
    steps = [p.step for p in mine]  # one count per run of the loop (CSF2's shape step may run twice)
    assert steps[0] == 1 and all(b == a + 1 or b == 1 for a, b in zip(steps, steps[1:])), steps
    assert all(p.total is None or p.step <= p.total for p in mine)
    if name == "empnd":
        assert steps[-1] == rec.iterations


def test_progress_bars_draw_one_bar_per_stage_and_close():
    out = io.StringIO()
    with ProgressBars(out, mininterval=0) as bars, listen(bars):
        for i in range(1, 4):
            report("empnd", "EM", i, 10, cost=-3.0)
        report("empnd", "EM", 1, 10)  # the loop runs again: the bar starts over
        report("pr", "L-BFGS", 2)
    text = out.getvalue()
    assert "empnd: EM:  30%" in text and "cost=-3" in text and "empnd: EM:  10%" in text
    assert "pr: L-BFGS: 2it" in text


def test_cli_solve_shows_progress_on_request_only(tmp_path, capsys):
    f = tmp_path / "s.npz"
    lowrank_sequence(40, 12, 2, seed=1).save(f)
    assert main(["solve", str(f), "-m", "emppca"]) == 0
    assert capsys.readouterr().err == ""  # stderr is not a terminal here
    assert main(["solve", str(f), "-m", "emppca", "--progress", "always"]) == 0
    assert "emppca: EM" in capsys.readouterr().err
    assert main(["solve", str(f), "-m", "emppca", "--progress", "sometimes"]) == 2
