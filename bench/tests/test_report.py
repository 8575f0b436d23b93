"""The benchmark's report keeps, per method, the fastest of several interleaved rounds, and checks
the issue's targets against the right rows, on the figures themselves."""

from bench import report
from bench.profile import kernel_shares


def _run(total_ms: float, tag: str) -> dict:
    return {"cold_ms": {"total": total_ms}, "tag": tag}


def test_fastest_round_is_kept_and_every_round_recorded():
    results: dict = {}
    for total, tag in [(500.0, "first"), (300.0, "second"), (400.0, "third")]:
        report.keep_fastest(results, "server", _run(total, tag))
    assert results["server"]["tag"] == "second"
    assert results["server"]["round_totals_ms"] == [500.0, 300.0, 400.0]


def test_a_round_that_ran_replaces_an_earlier_failure():
    results = {"ort": {"error": "worker died"}}
    report.keep_fastest(results, "ort", _run(700.0, "ran"))
    assert results["ort"]["tag"] == "ran"
    assert results["ort"]["round_totals_ms"] == [700.0]


def _reduced_precision_line(res: dict) -> str:
    return next(line for line in report.targets(res) if line.startswith("* reduced-precision"))


def test_reduced_precision_target_reads_only_reduced_precision_variants():
    methods = {
        "server": _run(75_000.0, "fp32"),
        "server-int8": _run(28_000.0, "int8"),
        "server-graph0.1": _run(20_000.0, "fp32 graph"),
    }
    res = {"sizes": {"640x512": {"methods": methods}}, "variant_precision": {"int8": "int8", "graph0.1": "fp32"}}
    assert _reduced_precision_line(res) == "* reduced-precision 640x512 view <= 30 s: met (int8 28.0 s)"
    methods["server-int8"] = _run(31_000.0, "int8")
    assert _reduced_precision_line(res) == "* reduced-precision 640x512 view <= 30 s: NOT met (int8 31.0 s)"
    res["variant_precision"]["int8"] = "fp32"
    assert _reduced_precision_line(res).endswith("not measured (no data)")


def test_profile_shares_leave_container_ops_out():
    """A Loop's kernel time is its body's nodes', which the profile lists too: counted once."""
    shares = kernel_shares({"Gemm": 30.0, "Loop": 25.0, "Softmax": 20.0, "MatMul": 10.0})
    assert shares["kernel_ms"] == 60.0
    assert "Loop" not in shares["by_op_ms"] and "Loop" not in shares["by_op_share"]
    assert list(shares["by_op_share"]) == ["Gemm", "Softmax", "MatMul"]
    assert abs(sum(shares["by_op_share"].values()) - 1.0) < 1e-12


def test_targets_are_checked_on_the_figures_not_on_their_rounded_text():
    res = {
        "sizes": {"160x128": {"methods": {"server": {**_run(1000.0, "server"), "ratio_to_torch": {"total": 0.504}}}}}
    }
    line = next(line for line in report.targets(res) if line.startswith("* end-to-end"))
    assert line == "* end-to-end fp32 view <= 0.5x PyTorch eager: NOT met (160x128 0.50x)"
