"""``machine.json``: which kind of CPU trained which stretch of a run (the kernels' rounding depends on it), and the
report naming the pairs whose two runs trained on different kinds."""

from __future__ import annotations

import json

import pytest

from kc_splatfacto.analysis import report
from kc_splatfacto.study.machine import (
    cpu_kind,
    cpu_model_name,
    machine_kinds,
    machine_signature,
    read_machines,
    record_machine,
)

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 26
model\t\t: 2
model name\t: AMD EPYC 9B45
flags\t\t: fpu vme avx2 avx512f

processor\t: 1
model name\t: AMD EPYC 9B45
"""


def test_cpu_model_name_is_the_first_model_name_line():
    assert cpu_model_name(CPUINFO) == "AMD EPYC 9B45"
    assert cpu_model_name("processor : 0\nmodel name :   \n") not in ("", None)  # blank name: a fallback, not ""


def test_cpu_kind_names_the_llvm_cpu_and_its_vector_features_widest_first():
    assert cpu_kind("znver5", {"fma": True, "avx2": True, "avx512f": True, "sse2": True}) == "znver5 avx512f avx2 fma"
    # the same CPU name with AVX-512 masked off (a VM) is another kind: its kernels round differently
    assert cpu_kind("znver5", {"fma": True, "avx2": True, "avx512f": False}) == "znver5 avx2 fma"
    assert cpu_kind("", {}) == "unknown"


def test_machine_signature_of_this_machine():
    signature = machine_signature()
    assert signature["kind"].split()[0] == signature["llvm_cpu"] and signature["llvm_cpu"]
    assert {"cpu_model", "arch", "numba", "llvmlite", "torch"} <= set(signature)
    json.dumps(signature)  # recorded as JSON


def test_record_machine_keeps_one_entry_per_stretch_of_training(tmp_path):
    a = {"kind": "znver3 avx2 fma"}
    b = {"kind": "znver5 avx512f avx2 fma"}
    assert read_machines(tmp_path) == []  # runs made before machine.json existed
    record_machine(tmp_path, 0, threads=1, signature=a)
    record_machine(tmp_path, 3000, threads=1, signature=b)  # continued on another machine
    entries = read_machines(tmp_path)
    assert [(e["from_step"], e["kind"], e["threads"]) for e in entries] == [(0, a["kind"], 1), (3000, b["kind"], 1)]
    assert machine_kinds(entries) == "znver3 avx2 fma + znver5 avx512f avx2 fma"
    # continued again from an earlier checkpoint: the stretch from 3000 was redone, its entry goes
    record_machine(tmp_path, 2000, threads=2, signature=a)
    assert [(e["from_step"], e["kind"]) for e in read_machines(tmp_path)] == [(0, a["kind"]), (2000, a["kind"])]
    assert machine_kinds(read_machines(tmp_path)) == a["kind"]
    # started again from step 0: a new list
    record_machine(tmp_path, 0, threads=1, signature=b)
    assert [e["kind"] for e in read_machines(tmp_path)] == [b["kind"]]


@pytest.mark.parametrize("content", ["{not json", '{"kind": "x"}', '[{"from_step": 0}]'])
def test_a_broken_machine_json_is_an_error_naming_the_file(tmp_path, content):
    (tmp_path / "machine.json").write_text(content)
    with pytest.raises(ValueError, match="machine.json"):
        read_machines(tmp_path)


def _row(method, seed, psnr, cpu):
    return {"scene": "s", "method": method, "seed": seed, "step": 100, "elapsed_s": 1.0, "train_s": 1.0,
            "train_cpu_s": 1.0, "psnr": psnr, "ssim": 0.5, "lpips": None, "lpips_net": None, "lpips_vgg": None,
            "num_images": 2, "run_dir": "", "cpu": cpu}


def test_report_names_the_pairs_whose_runs_trained_on_different_cpus(tmp_path):
    rows = [
        _row("splatfacto", 0, 20.0, "znver3 avx2 fma"), _row("kc", 0, 20.5, "znver3 avx2 fma"),  # same kind
        _row("splatfacto", 1, 21.0, "znver3 avx2 fma"), _row("kc", 1, 20.0, "znver5 avx512f avx2 fma"),  # mixed
        _row("splatfacto", 2, 22.0, ""), _row("kc", 2, 22.5, "znver5 avx512f avx2 fma"),  # one not recorded
    ]
    (entry,) = report.paired_deltas(rows, "splatfacto")
    assert entry["seeds"] == [0, 1, 2] and entry["mixed_cpu_seeds"] == [1]
    assert entry["psnr_db"] == pytest.approx([0.5, -1.0, 0.5])  # kept in the estimate, only named
    table = report.markdown_paired_table([entry], "splatfacto")
    assert "different kinds of CPU" in table and "s kc seed 1" in table and "seed 2" not in table.split("CPU")[-1]
    # the cpu column survives the CSV round trip the report is re-read from
    paths = report.write_report(rows, tmp_path, baseline="splatfacto")
    assert [r["cpu"] for r in report.read_rows_csv(paths["csv"])] == [r["cpu"] for r in rows]
    same = [dict(r, cpu="znver3 avx2 fma") for r in rows]
    assert report.paired_deltas(same, "splatfacto")[0]["mixed_cpu_seeds"] == []
    assert "different kinds of CPU" not in report.markdown_paired_table(report.paired_deltas(same, "splatfacto"),
                                                                        "splatfacto")
