"""What a run leaves behind and how it is read back: the output paths, the dashboard's layout (entities,
blueprint, the contour recording), where the telemetry goes (its sinks, the viewer, the .rrd's footer),
the recording reader, how a run's summary reads on the terminal, and the pieces of the HTML reports (page
helpers, an SVG trend plot).

May import :mod:`rt_ident.estimators` and :mod:`rt_ident.axis`.
"""
