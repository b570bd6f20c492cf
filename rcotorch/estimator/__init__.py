"""The identified subsystem: the RCMR estimator, its parameter map (masks and ties), its
transfer-function export, change detection and tracking, and frequency-response analysis.
"""
