"""The run kinds: ``subject`` (one avatar per capture), ``autoencoder`` (across the people of a THUman-layout set)
and ``rigid`` (one object). One package per kind, their table (``kinds``), the requests the commands build
(``requests``) and the fit every caller runs (``fit``); docs/design.md, "Run kinds"."""
