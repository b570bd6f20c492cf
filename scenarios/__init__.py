"""The scenarios shipped with rcotorch: the seed paper's examples and a real-data case, one module each.

Installed as the package ``rcotorch.scenarios``; ``rcotorch list`` lists them, ``rcotorch show NAME`` prints a
scenario's settings, ``rcotorch run NAME`` runs it. Each module defines ``SCENARIO`` (see ``rcotorch.run.scenario``).

``list`` and ``show`` read the scenarios' class attributes only: the modules import torch, python-control, scipy,
matplotlib and the heavier parts of rcotorch (models, analysis, intervals, datasets) inside the functions that use
them, so that these commands start without loading them.
"""
