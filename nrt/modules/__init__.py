"""What a stage learns from, in one-way layers: encodings and networks
(:mod:`~nrt.modules.encodings`) <- fields (:mod:`~nrt.modules.fields`) <- renderers
(:mod:`~nrt.modules.renderers`); objectives (:mod:`nrt.losses`) and stages
(:mod:`nrt.stages`) sit above them. tests/test_layout.py keeps the order."""
