"""The speaker's own 3D delegate: the full-face mesh fitted to the enrolled model, animated by
it (sparse-to-dense transfer), textured from the enrolment frames (METHOD.md §2, ``tex lin``),
and its export to glTF 2.0."""
