"""The evaluation's condition and model names, importable without the tracker (the CLI's
help lists them; importing the experiments pulled numba and SciPy into every command)."""

MODELS = ("la_cst", "la_lin", "la_quad", "tex_cst", "tex_lin", "la_lin_nelder_mead")
CONDITIONS = ("postures", "teleconference", "desk", "noise", "gain", "blur", "light",
              "occlusion", "hand_slide")
