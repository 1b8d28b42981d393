"""The paper's studies on this project: running them (run_studies.sh, time_samplers.py) and turning their
runs into docs/results.md (make_results.py, one module per study) and docs/outdoor_profile.md
(outdoor_profile.py). Run the modules from the repository root as `python -m studies.<module>`; see
studies/README.md."""
