"""The numbers docs/own-problem.md and docs/tuning.md state about their examples and studies are the results on
record: ``benchmarks/docs_examples.py --claims`` prints each statement from benchmarks/results/docs_examples.json,
friction_study.json, tune_study.json and tune_study_impedance.json, every number rounded as the doc prints it
(tolerance: half a unit of the last printed digit; a bound such as "within 0.003" rounded up), and each must
stand in its doc. A doc edited without its results, or results measured again without the doc, fail here. The
scripts themselves are not run (see benchmarks/README.md for how to measure again)."""

import re

from bench_scripts import ROOT, run_script


def _normal(text: str) -> str:
    return re.sub(r"\s+", " ", text)


def test_the_docs_state_the_numbers_the_scripts_measured():
    printed = run_script("docs_examples", "--claims", timeout=120).stdout.splitlines()
    claims = [line.split("\t", 1) for line in printed if "\t" in line]
    assert len(claims) > 40 and {doc for doc, _ in claims} == {"own-problem.md", "tuning.md"}
    docs = {doc: _normal((ROOT / "docs" / doc).read_text()) for doc, _ in claims}
    missing = [f"{doc}: {text}" for doc, text in claims if _normal(text) not in docs[doc]]
    assert not missing, "not in the docs as measured:\n" + "\n".join(missing)
