"""Records of notebook 08's theory check (appendix 08c): computed once, read back bit for bit, refused when damaged."""

import hashlib
import json

import numpy as np
import pandas as pd
import pytest

from pemamoe.nets import make_actor
from pemamoe.theory_records import (
    TheoryRecordError,
    find_theory_record,
    parameters_hash,
    read_theory_record,
    round_reported,
    theory_parameters,
    theory_record,
    theory_record_path,
    verify_theory_record,
)
from pemamoe.toy_tracking import (TrackerConfig, TrackingProblemConfig, paired_distance, routing_stability_samples,
                                  run_many)

PROBLEM = TrackingProblemConfig(n_phases=3, probe_size=32)


def _jobs(iterations=16, **kw):
    base = dict(iterations=iterations, n_switches=2, batch=8, noise_epochs=3, **kw)
    return [(PROBLEM, TrackerConfig(controller="off", **base), 0, 3, False),
            (PROBLEM, TrackerConfig(controller="noise", noise_gamma=0.05, **base), 0, 3, False)]


def _compute_small(jobs):
    """A tiny version of notebook 08's experiments: a noisy run against its twin, and a routing
    sweep of an actor; the tables and values carry every dtype the notebook's records do."""
    def compute():
        clean, noisy = run_many(jobs)
        pairs = pd.DataFrame([{"kind": "pemamoe", "gamma": 0.05, "K": 2, "seed": 3, "sweeps": "gamma+window N",
                               "schedule_matches": True, "clean_regret": clean.total_regret,
                               **paired_distance(clean, noisy)}])
        import torch

        torch.manual_seed(0)
        actor = make_actor("pemamoe", 4, 2)
        rng = np.random.default_rng(1)
        states = rng.standard_normal((6, 4))
        samples = routing_stability_samples(actor, states, [("router", 1e-2), ("expert1", 1e-1), ("joint", 1e-2)], rng,
                                            n_samples=16, tie=np.r_[np.zeros(4, bool), np.ones(2, bool)])
        values = {"n_experts": 3, "spread": states.std(0), "gap": np.float32(0.1), "regret": noisy.total_regret}
        return {"pairs": pairs, "samples": samples}, values
    return compute


def _counting(compute):
    calls = []

    def wrapped():
        calls.append(1)
        return compute()
    return wrapped, calls


def test_round_trip_is_exact_and_a_second_run_reads(tmp_path):
    jobs = _jobs()
    params = theory_parameters({"iterations": 16, "seed": 3}, jobs)
    computed = _compute_small(jobs)()
    compute, calls = _counting(lambda: computed)
    lines = []
    tables, values = theory_record(tmp_path, "ci", "noise", params, compute, say=lines.append)
    assert calls == [1] and "computing (no record)" in lines[0]
    for name, frame in computed[0].items():
        pd.testing.assert_frame_equal(tables[name], frame, check_exact=True)
    assert values["n_experts"] == 3 and values["regret"] == computed[1]["regret"]
    assert values["spread"] == computed[1]["spread"].tolist() and values["gap"] == float(np.float32(0.1))
    again, values2 = theory_record(tmp_path, "ci", "noise", params, compute, say=lines.append)
    assert calls == [1] and "read" in lines[-1]  # read, not computed
    for name, frame in computed[0].items():
        pd.testing.assert_frame_equal(again[name], frame, check_exact=True)
    assert values2 == values
    marker_path = theory_record_path(tmp_path, "ci", "noise")
    marker = json.loads(marker_path.read_text())
    assert marker["parameters_hash"] == parameters_hash(params) and marker["parameters"] == params
    for name, seal in marker["tables"].items():
        data = marker_path.with_name(seal["file"]).read_bytes()
        assert seal["sha256"] == hashlib.sha256(data).hexdigest() and seal["rows"] == len(computed[0][name])
    assert json.loads(marker_path.with_name(marker_path.stem + ".timing.json").read_text())["compute_s"] >= 0
    assert not list(marker_path.parent.glob("*.tmp"))


def test_parameters_name_what_the_results_depend_on():
    jobs = _jobs()
    h = parameters_hash(theory_parameters({"T": 16}, jobs))
    assert h == parameters_hash(theory_parameters({"T": 16}, [j[:4] + (True,) for j in jobs]))  # keep_actor: no effect
    assert h != parameters_hash(theory_parameters({"T": 16}, _jobs(lr=1e-3)))  # a learner setting
    assert h != parameters_hash(theory_parameters({"T": 16}, [(j[0], j[1], j[2], 4, False) for j in jobs]))  # a seed
    assert h != parameters_hash(theory_parameters({"T": 17}, jobs))  # a setting of the notebook
    assert h != parameters_hash(theory_parameters({"T": 16}, jobs[:1]))


def test_a_changed_network_default_is_a_change_of_parameters(monkeypatch):
    import pemamoe.theory_records as tt

    jobs = _jobs()
    before = parameters_hash(theory_parameters({}, jobs))
    real = tt.NetConfig
    monkeypatch.setattr(tt, "NetConfig", lambda **kw: real(**kw, gain_router=0.5))
    assert parameters_hash(theory_parameters({}, jobs)) != before


def test_a_record_with_other_parameters_is_not_used(tmp_path):
    old = theory_parameters({"T": 10, "seed": 0})
    new = theory_parameters({"T": 20, "seed": 0})
    frame_old, frame_new = pd.DataFrame({"x": [1.0]}), pd.DataFrame({"x": [2.0]})
    theory_record(tmp_path, "ci", "regret", old, lambda: ({"runs": frame_old}, {}), say=lambda s: None)
    compute, calls = _counting(lambda: ({"runs": frame_new}, {}))
    lines = []
    tables, _ = theory_record(tmp_path, "ci", "regret", new, compute, say=lines.append)
    assert calls == [1] and tables["runs"].x.tolist() == [2.0]
    assert "holds other parameters (settings.T)" in lines[0]
    marker = theory_record_path(tmp_path, "ci", "regret")
    with pytest.raises(TheoryRecordError, match=r"was made with other parameters .*settings\.T") as err:
        read_theory_record(marker, old)  # a reader that names the parameters is refused
    assert str(marker) in str(err.value) and "\n" not in str(err.value)
    assert read_theory_record(marker, new)[0]["runs"].x.tolist() == [2.0]


def test_another_scales_record_of_the_same_parameters_is_read(tmp_path):
    params = theory_parameters({"T": 10})
    theory_record(tmp_path, "medium", "noise", params, lambda: ({"pairs": pd.DataFrame({"x": [1.5]})}, {}),
                  say=lambda s: None)
    compute, calls = _counting(lambda: ({"pairs": pd.DataFrame({"x": [9.0]})}, {}))
    tables, _ = theory_record(tmp_path, "small", "noise", params, compute, say=lambda s: None)
    assert calls == [] and tables["pairs"].x.tolist() == [1.5]
    assert find_theory_record(tmp_path, "small", "noise", params) == theory_record_path(tmp_path, "medium", "noise")
    assert not theory_record_path(tmp_path, "small", "noise").exists()
    assert find_theory_record(tmp_path, "small", "noise", theory_parameters({"T": 11})) is None  # other parameters: none


def _damage_table(marker):
    table = marker.with_name(marker.stem + ".samples.parquet")
    table.write_bytes(table.read_bytes()[:-2] + b"\0\0")
    return table


def _drop_table(marker):
    table = marker.with_name(marker.stem + ".samples.parquet")
    table.unlink()
    return table


def _edit_marker(change):
    def damage(marker):
        obj = json.loads(marker.read_text())
        change(obj)
        marker.write_text(json.dumps(obj))
        return marker
    return damage


def _garbage_marker(marker):
    marker.write_text('{"format": 1, "experiment": "rout')
    return marker


DAMAGES = {
    "table changed": (_damage_table, "differs from the file its marker routing"),  # routing.json, or routing-n3.json after a bump
    "table missing": (_drop_table, "is missing"),
    "marker not JSON": (_garbage_marker, "cannot be read"),
    "parameters edited": (_edit_marker(lambda m: m["parameters"]["settings"].update(T=11)), "parameters edited"),
    "values edited": (_edit_marker(lambda m: m["values"].update(gap=0.5)), "values that differ"),
    "field missing": (_edit_marker(lambda m: m.pop("tables")), "lacks the field(s) tables"),
    "other format": (_edit_marker(lambda m: m.update(format=99)), "has format 99"),
    "renamed": (_edit_marker(lambda m: m.update(experiment="noise")), "is the record of 'noise'"),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_record_is_refused_naming_the_file(tmp_path, damage):
    params = theory_parameters({"T": 10})
    theory_record(tmp_path, "medium", "routing", params,
                  lambda: ({"samples": pd.DataFrame({"l1": [0.25, 0.5], "tie": [False, True]})}, {"gap": 0.125}),
                  say=lambda s: None)
    marker = theory_record_path(tmp_path, "medium", "routing")
    do, problem = DAMAGES[damage]
    named = do(marker)
    compute, calls = _counting(lambda: ({"samples": pd.DataFrame({"l1": [1.0]})}, {}))
    with pytest.raises(TheoryRecordError) as err:
        theory_record(tmp_path, "medium", "routing", params, compute, say=lambda s: None)
    message = str(err.value)
    assert calls == [] and "\n" not in message
    assert message.startswith(f"theory record {named}: ") and problem in message
    # retrain=True ignores the records: it computes and writes a sound one in place of the damaged one
    tables, _ = theory_record(tmp_path, "medium", "routing", params, compute, retrain=True, say=lambda s: None)
    assert calls == [1] and tables["samples"].l1.tolist() == [1.0]
    assert verify_theory_record(marker, params) is not None


def test_stale_tables_are_removed_and_bad_tables_refused(tmp_path):
    marker = theory_record_path(tmp_path, "ci", "regret")
    params = theory_parameters({"T": 1})
    theory_record(tmp_path, "ci", "regret", params,
                  lambda: ({"runs": pd.DataFrame({"x": [1.0]}), "curves": pd.DataFrame({"y": [2.0]})}, {}), say=lambda s: None)
    theory_record(tmp_path, "ci", "regret", params, lambda: ({"runs": pd.DataFrame({"x": [1.0]})}, {}), retrain=True,
                  say=lambda s: None)
    assert sorted(p.name for p in marker.parent.glob(marker.stem + ".*.parquet")) == [marker.stem + ".runs.parquet"]
    with pytest.raises(ValueError, match="default index"):
        theory_record(tmp_path, "ci", "regret", params, lambda: ({"runs": pd.DataFrame({"x": [1.0]}, index=[5])}, {}),
                      retrain=True, say=lambda s: None)
    with pytest.raises(ValueError, match="experiment must match"):
        theory_record_path(tmp_path, "ci", "../x")


def test_round_reported_drops_the_bits_that_differ_between_processors():
    # the same two-regressor fit with OpenBLAS's default and its generic kernels (OPENBLAS_CORETYPE=Prescott)
    frame = pd.DataFrame({"fit": ["a", "b", "c"], "slope": [0.019624571464290558, 0.019624571464290613, float("nan")],
                          "n": [3, 4, 5], "ok": [True, False, True]})
    out = round_reported(frame)
    assert out.slope[0] == out.slope[1] == 0.0196246 and np.isnan(out.slope[2])
    assert out[["fit", "n", "ok"]].equals(frame[["fit", "n", "ok"]])
    assert frame.slope[0] == 0.019624571464290558  # a copy
