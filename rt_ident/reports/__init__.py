"""What a user asks for after (or instead of) a run: the paper's tables and figures, the noise
study, offline identification of a recording, and the benchmarks.

May import everything below it (:mod:`rt_ident.compose` and the layers under it, :mod:`drivers` included).
"""
