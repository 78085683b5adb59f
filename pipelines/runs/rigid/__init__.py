"""The rigid-object run kind (supplement Table B): fit and evaluation of RT-NeRF, RT-NeRF w/o xi and RP-NeRF
(``session``)."""
