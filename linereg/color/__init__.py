"""The stages of colorization (``linereg.colorization`` composes them): ``surface`` local spacing and
normals, ``project`` points into photos, ``depth`` visibility from point splats, ``gains`` exposure,
``blend`` weighted colours, ``engine`` the two passes as tasks over chunks, ``config`` their settings."""
