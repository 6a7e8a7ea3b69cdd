"""The motion of record, on joint positions (..., T, 22, 3): made rigid (``rigid``, on the rest skeleton and the
rotations of ``fit``), its feet held still (``feet``), and measured as animators read it (``quality``: skating,
penetration, floating, jitter; the skating rule that ``feet`` cleans by). Below generation, export and evaluation,
which all use it; it imports only lsgan.data."""
