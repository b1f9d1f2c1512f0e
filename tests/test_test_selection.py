"""`make test-fast`'s selection (tests/conftest.py): every slow module and test it names exists,
so a renamed test cannot slip into the fast set unnoticed; the Makefile and README say both."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import SLOW_MODULES, SLOW_TESTS, is_slow

REPO = Path(__file__).resolve().parents[1]


def test_every_slow_module_and_test_named_exists():
    for module in SLOW_MODULES:
        assert (REPO / module).exists(), f"tests/conftest.py SLOW_MODULES names {module}, which does not exist"
    for test in SLOW_TESTS:
        path, _, name = test.partition("::")
        source = (REPO / path).read_text()
        assert re.search(rf"^def {re.escape(name)}", source, re.M), f"SLOW_TESTS names {test}, which does not exist"


def test_is_slow_by_module_by_test_and_by_parametrised_test():
    assert is_slow("tests/methods/calc/test_calc.py::test_anything")
    assert is_slow("tests/cli/test_extract.py::test_torchrun_two_processes_write_the_npz_one_process_writes")
    assert is_slow("tests/descriptors/test_pipeline.py::test_a_folder_streams_in_memory_far_below_its_decoded_size[1]")
    assert not is_slow("tests/descriptors/test_pipeline.py::test_batches_come_in_order_with_the_loaders_values[0-0]")


def test_make_has_test_and_test_fast_and_the_readme_says_both():
    makefile = (REPO / "Makefile").read_text()
    assert re.search(r'^test-fast: .*\n\t.*pytest -q -m "not slow" tests$', makefile, re.M)
    assert re.search(r"^test: .*\n\t.*pytest -q tests$", makefile, re.M)
    readme = (REPO / "README.md").read_text()
    assert "make test-fast" in readme and "make test " in readme
