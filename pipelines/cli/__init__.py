"""Console scripts, one module each (``narf-<name>`` runs ``pipelines.cli.<name>:entrypoint``), and their shared
plumbing (``common``: the help formatter and the one-line error handling with exit code 2).
"""
