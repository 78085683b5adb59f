"""The NARF supplement's tables as runnable experiments (``narf-experiments``)."""
