"""What a stage learns and how it learns it, in one-way layers: encodings and networks
(:mod:`~nrt.modules.encodings`) <- fields (:mod:`~nrt.modules.fields`) <- renderers
(:mod:`~nrt.modules.renderers`) <- objectives (:mod:`nrt.losses`) <- stages
(:mod:`~nrt.modules.stages`). tests/test_layout.py keeps the order."""
