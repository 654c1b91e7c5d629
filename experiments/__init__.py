"""Experiment harnesses behind the scripts: simulate, calibrate, compare against the truth.

Above the pipeline (they run whole calibrations); nothing in the library imports them.
"""
