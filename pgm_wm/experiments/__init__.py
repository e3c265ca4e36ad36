"""Multi-seed experiments of the model chapters (issue 12): statistics, results files, runners.

* :mod:`pgm_wm.experiments.stats`   two-level (seeds × test windows) bootstrap intervals;
* :mod:`pgm_wm.experiments.results` results files with provenance, tables and computed conclusions.

Submodules are imported explicitly.
"""
