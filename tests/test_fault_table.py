"""The table "Faults and exit codes" in docs/cli.md names, for each fault, the tests that reproduce it: every
test it names exists (a test renamed or removed would leave the table promising what nothing checks)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_test_the_fault_table_names_exists():
    text = (ROOT / "docs" / "cli.md").read_text()
    table = text[text.index("## Faults and exit codes"):]
    named = re.findall(r"(test_\w+\.py)::(test_\w+)", table)
    assert len(named) > 40
    missing = []
    for file, test in named:
        source = (ROOT / "tests" / file).read_text() if (ROOT / "tests" / file).is_file() else ""
        if not re.search(rf"^def {test}\(", source, re.M):
            missing.append(f"{file}::{test}")
    assert not missing, missing
