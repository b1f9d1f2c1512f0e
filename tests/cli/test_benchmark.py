"""`fdnet benchmark` runs and reports every figure with its reference (no timing is asserted)."""

import json

from fdnet.cli import main


def test_quick_benchmark_reports_figures_and_ratios(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["benchmark", "--quick", "--threads", "1", "--methods", "raw,sad", "--num-images", "4",
                 "--map-size", "200", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["gemm_gflops_fp32"] > 0
    fdnet_512 = report["fdnet_extraction_ms"]["512"]
    assert fdnet_512["paper_gpu"] == 21.2 and fdnet_512["bf16_batch32"] > 0
    assert report["matching_ms"]["512"]["paper_gpu"] == 0.35
    assert set(report["method_extraction_ms"]) == {"raw", "sad"}
    assert report["ratio_vs_sad"]["sad"] == 1.0
    printed = capsys.readouterr().out
    assert "paper/ours" in printed and "GFLOP/s" in printed


def test_benchmark_reports_a_method_it_cannot_run(tmp_path, capsys):
    assert main(["benchmark", "--quick", "--threads", "1", "--methods", "hybridnet", "--num-images", "2",
                 "--map-size", "100"]) == 0
    assert "hybridnet  skipped" in capsys.readouterr().out
