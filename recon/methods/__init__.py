"""The per-segment reconstruction methods: ``paper`` (Eq. 4) and ``anchored`` (ours).

Each takes one segment's points, what it follows (:class:`recon.classify.SegmentKind`), the scan
model (or None), the parameters and N_P's half-width, and returns a
:class:`recon.methods.common.SegmentResult`.
"""
