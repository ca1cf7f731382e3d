"""What a run leaves behind and how it is read back: the output paths, the dashboard's layout (entities,
blueprint, the contour recording) and the recording reader.

May import :mod:`rt_ident.estimators` and :mod:`rt_ident.axis`.
"""
