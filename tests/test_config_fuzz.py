"""Fuzzed run configs never end in a traceback: each either passes the run's start-up checks
(``rt_ident.config.from_mapping`` + :func:`rt_ident.compose.preflight.preflight`: everything a
run builds before it starts a process or enables a device) or is refused with one line naming a
field. The shipped configs are mutated with wrong types, negative, NaN, infinite and huge
numbers, unknown keys and sections that are not tables; the same configs as TOML files go
through ``rt-ident run`` itself (its loop replaced, so nothing runs). Deterministic
(``derandomize``), bounded, a few seconds."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import re
import sys
import tomllib
from pathlib import Path
from unittest import mock

from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from rt_ident.compose.preflight import preflight
from rt_ident.config import RunConfig, from_mapping
from rt_ident.errors import RtIdentError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
BASES = {name: tomllib.loads((CONFIGS / name).read_text())
         for name in ("sim.toml", "serial-virtual.toml", "canopen-virtual.toml", "xy-sim.toml", "sim-load-change.toml")}
for _data in BASES.values():
    _data["loop"]["realtime"] = False
SECTIONS = set(RunConfig.model_fields)

#: (section, key) pairs the fuzzer sets: existing fields of every section, and keys nobody knows
KEYS = [("axis", k) for k in ("I1", "I2", "B", "K", "lead", "mass")] + \
    [("backend", k) for k in ("name", "emulate", "sample_period", "torque_limit", "rated_torque", "counts_per_rev",
                              "scale_resolution", "interface", "sync_rate_hz", "sample_rate_hz", "node_id",
                              "torque_constant", "paced", "samples_per_read", "travel", "axis", "friction",
                              "baudrate")] + \
    [("safety", k) for k in ("window", "max_decel", "watchdog_ticks", "stuck_torque", "torque_hold", "windw")] + \
    [("loop", k) for k in ("tick_hz", "duration", "warmup_periods", "max_sleep_us", "realtime", "compiled_tick")] + \
    [("excitation", k) for k in ("kind", "period_samples", "band", "peak", "seed")] + \
    [("estimator", k) for k in ("method", "forgetting", "kalman_process_noise", "per_sample", "svf_hz",
                                "svf_memory_s", "svf_quanta", "model", "friction_hz", "friction_memory_s")] + \
    [("control", k) for k in ("mode", "bandwidth_hz", "effort", "conservative_bandwidth_hz", "conservative_load",
                              "phase_margin_deg", "family_factors", "max_error_m", "delay_ticks")] + \
    [("telemetry", k) for k in ("sink", "rate_hz", "port", "bind_ip", "publish_every_ticks", "connect_url")] + \
    [("reference", k) for k in ("kind", "amplitude", "frequency_hz")] + \
    [("plant", k) for k in ("change", "friction")] + \
    [("emulator", k) for k in ("seed", "torque_meas_noise", "travel", "heartbeat_timeout", "faults")] + \
    [("recording", k) for k in ("enabled", "path")] + \
    [("nonsense", "key")]

NASTY = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, 0.0, -1, -1e-9, 1e-12, 1e-6, 1e300, -1e300, 10**30, 2**62,
                     True, False, "", "abc", "1e3", "sim", "serial", "canopen", "socketcan", "virtual", "off", [],
                     [0.04, -0.04], [math.nan, 0.04], [-1e300, 1e300], [1, 2, 3], [0.5, 2.0], {}, {"a": 1},
                     [{"at": 0.5, "I2": 1e300}], [{"at": -1}], {"preset": "thomson"}, {"Fc1": math.inf},
                     100.0, 3333.0, 3334.0, 99.9, 1e9, 0.5, 20, 4, 512, 65536]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-2**63, max_value=2**63 - 1),
    st.text(st.characters(exclude_categories=("Cs",)), max_size=6),       # any text a UTF-8 file can hold
)


@st.composite
def mutation(draw):
    kind = draw(st.sampled_from(["set", "set", "set", "section-not-a-table", "drop-section", "axes"]))
    if kind == "set":
        section, key = draw(st.sampled_from(KEYS))
        return ("set", section, key, draw(NASTY))
    if kind == "section-not-a-table":
        return ("replace", draw(st.sampled_from(sorted(SECTIONS - {"source"}))),
                draw(st.sampled_from([5, "x", [1, 2], True, 1.5])))
    if kind == "drop-section":
        return ("drop", draw(st.sampled_from(["axis", "backend", "safety", "loop", "excitation", "control"])), None)
    return ("replace", "axes", draw(st.sampled_from([5, {"x": 5}, {"x": {"loop": {}}}, {"x": {"safety": {"window": 1}}},
                                                     {"x": {"backend": {"torque_limit": 1e9}}}, {"": {}}])))


def _mutated(base: str, mutations: list) -> dict:
    data = copy.deepcopy(BASES[base])
    for kind, section, *rest in mutations:
        if kind == "set":
            key, value = rest
            if not isinstance(data.get(section), dict):
                data[section] = {}
            data[section][key] = value
        elif kind == "replace":
            data[section] = rest[0]
        else:
            data.pop(section, None)
    return data


def _field(message: str, extra_roots: set[str] = frozenset()) -> str:
    """The field a one-line error names (its root a config section, or ``extra_roots``)."""
    assert "\n" not in message and "Traceback" not in message, message
    m = re.match(r"^(?P<field>[^:\s][^:]*?): \S", message)
    assert m, f"no field named: {message!r}"
    field = m.group("field")
    root = field if field in extra_roots else re.split(r"[.\[ ]", field, maxsplit=1)[0]
    assert root in SECTIONS | {"config"} | set(extra_roots), f"{field!r} names no setting: {message!r}"
    return field


def _check(data: dict) -> str:
    try:
        preflight(from_mapping(data, source="fuzz.toml"))
    except RtIdentError as exc:
        _field(str(exc), set(data) if isinstance(data, dict) else set())
        return "refused"
    return "accepted"


@settings(derandomize=True, max_examples=300, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(base=st.sampled_from(sorted(BASES)), mutations=st.lists(mutation(), min_size=1, max_size=3))
def test_fuzzed_configs_pass_the_start_up_checks_or_are_refused_in_one_line_naming_a_field(base, mutations):
    event(_check(_mutated(base, mutations)))


def test_the_reported_cases_are_refused_in_one_line_naming_their_field():
    """Fuzzed cases kept as fixed examples: each is refused in one line naming its field."""
    cases = {("safety", "window"): [0.04, -0.04], ("backend", "sample_period"): 1e-12, ("axis", "I1"): 1e300,
             ("loop", "tick_hz"): math.nan, ("backend", "torque_limit"): 1e9}
    for (section, key), value in cases.items():
        data = _mutated("sim.toml", [("set", section, key, value)])
        with contextlib.suppress(RtIdentError):
            preflight(from_mapping(data))
            raise AssertionError(f"{section}.{key} = {value!r} accepted")
        assert _check(data) == "refused"
    data = _mutated("sim.toml", [("set", "loop", "tick_hz", 0.1)])
    try:
        preflight(from_mapping(data))
    except RtIdentError as exc:
        assert _field(str(exc)) == "loop.tick_hz" and "spin_s" not in str(exc)


# ---------------------------------------------------------------------------------- the command line
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")     # TOML escapes DEL too
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"


def _toml(data: dict) -> str:
    """``data`` as TOML: plain keys first, then one table per section (nested tables inline)."""
    lines = [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for section, table in data.items():
        if isinstance(table, dict):
            lines.append(f"[{json.dumps(section)}]")
            lines += [f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


class _WouldRun(BaseException):
    """The run was about to start: every check passed (not an Exception: main() must not catch it)."""


@settings(derandomize=True, max_examples=120, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(base=st.sampled_from(sorted(BASES)), mutations=st.lists(mutation(), min_size=1, max_size=3))
def test_rt_ident_run_on_fuzzed_config_files_exits_2_with_one_line_naming_a_field(tmp_path_factory, base, mutations):
    from rt_ident import cli

    path = tmp_path_factory.mktemp("fuzz") / "fuzz.toml"
    data = _mutated(base, mutations)
    path.write_text(_toml(data))
    stderr = io.StringIO()

    def would_run(*args, **kwargs):
        raise _WouldRun

    argv = ["rt-ident", "run", str(path), "--no-telemetry"]
    with mock.patch("rt_ident.compose.run.run", would_run), mock.patch.object(sys, "argv", argv), \
            contextlib.redirect_stderr(stderr):
        try:
            cli.main()
        except _WouldRun:
            event("accepted")
            return
        except SystemExit as exc:
            code = exc.code
        else:
            raise AssertionError("rt-ident run returned without running or exiting")
    lines = [ln for ln in stderr.getvalue().splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), stderr.getvalue()
    event("refused")
    _field(lines[0].removeprefix("error: "), {str(path), "--rrd", "--connect", *data})   # an unknown section: its name
