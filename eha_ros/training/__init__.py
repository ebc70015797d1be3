"""Every build and training routine: the map databases, the surrogates' tables, fits and
networks, the health estimators' tables and networks.  Each module builds its artefacts with
``python -m eha_ros.training.<module>``.  Torch and scipy are imported here only.
"""
