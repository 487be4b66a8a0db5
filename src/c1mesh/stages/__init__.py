"""Layer 3: the fit's stages between reading and refining: frames, normals, gradients, curtain rules, the overshoot limiter."""
