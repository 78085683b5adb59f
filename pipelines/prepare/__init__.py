"""``narf-prepare-capture``: a multi-camera recording in, a capture out. ``run`` is the pipeline's table of contents
(its stages are the sub-packages, in order: ``sources``, ``sync``, ``people``, ``body``, ``layout``), ``request`` what
it is asked; ``compare`` and ``demo_data`` are tools beside it."""
