"""The service's JSON-lines logs are strict JSON: NaN and inf as null (as every JSON linereg writes)."""

import json
import logging
import math

import numpy as np

from service.logs import JsonFormatter


def test_a_log_line_is_strict_json_with_nan_as_null():
    record = logging.LogRecord("service", logging.INFO, __file__, 1, "query %s", ("q1",), None)
    record.fields = {"rms_px": math.nan, "ambiguity": math.inf, "shape": np.arange(2), "who": object()}
    line = JsonFormatter().format(record)
    doc = json.loads(line, parse_constant=lambda token: (_ for _ in ()).throw(ValueError(token)))
    assert doc["message"] == "query q1" and doc["rms_px"] is None and doc["ambiguity"] is None
    assert doc["shape"] == [0, 1] and doc["who"].startswith("<object")
