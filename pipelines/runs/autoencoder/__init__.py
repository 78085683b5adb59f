"""The autoencoder run kind: an image encoder and a latent-conditioned field trained across the people of a
THUman-layout set (``session``), evaluated on its splits and on SURREAL (``evaluation``), and rendered (``video``)."""
