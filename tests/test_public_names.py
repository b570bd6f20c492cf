"""Public names where users look for them: Scenario and Requirement beside rt.refine, and the import path of
earlier releases (rcotorch.scenario) still working, with a warning naming the new one."""

import subprocess
import sys


def test_scenario_and_requirement_are_public_and_the_old_import_path_works_with_a_warning():
    code = ("import warnings; warnings.simplefilter('error', DeprecationWarning)\n"
            "try:\n    from rcotorch.scenario import Scenario\nexcept DeprecationWarning as w:\n    print(w)\n"
            "warnings.simplefilter('ignore')\n"
            "from rcotorch.scenario import Scenario, Requirement\n"
            "import rcotorch as rt, rcotorch.run.scenario as new\n"
            "print(Scenario is new.Scenario is rt.Scenario, Requirement is new.Requirement is rt.Requirement)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "rcotorch.scenario is now rcotorch.run.scenario" in out and "rcotorch.Scenario" in out
    assert out.strip().endswith("True True")
