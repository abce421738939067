"""The paper's camera-by-path study (section II.C, III.B, IV.B), reproduced and scaled out on Dask.

``design`` builds the camera database (Latin Hypercube), ``catalogue`` the
sampling strategies and how they become points, ``evaluate`` one (camera,
strategy) Monte-Carlo row, ``store`` the resumable parquet results,
``runner`` the Dask stage, ``findings`` and ``figures`` the paper's
comparisons and Figures 8-10. See docs/survey.md.
"""
