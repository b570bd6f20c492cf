"""The scenarios shipped with rcotorch: the seed paper's examples and a real-data case, one module each.

Installed as the package ``rcotorch.scenarios``; ``rcotorch list`` lists them, ``rcotorch show NAME`` prints a
scenario's settings, ``rcotorch run NAME`` runs it. Each module defines ``SCENARIO`` (see ``rcotorch.scenario``).
"""
