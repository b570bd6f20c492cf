"""Measured data: recordings loaded from files, and the public data sets rcotorch obtains itself.
"""
