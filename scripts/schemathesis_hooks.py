"""schemathesis hooks for scripts/schemathesis.sh (loaded through SCHEMATHESIS_HOOKS).

Bodies generated from the schema never carry images that decode to their cameras' size, so
`POST /v1/scenes` would never answer 201 and the stateful phase would never follow its links
(render the scene, delete it). Half the JSON bodies drawn for that operation are replaced with
a valid scene: the first parity fixture case, its images in base64.
"""

import base64
import json
import pathlib

import schemathesis
from hypothesis import strategies as st

CASE = pathlib.Path(__file__).resolve().parent.parent / "tests/fixtures/parity/cases/opencv_64x96"


def valid_scene():
    request = json.loads((CASE / "request.json").read_text())
    for key in ("target", "outputs"):
        request.pop(key, None)
    for i, source in enumerate(request["sources"]):
        source["image"] = base64.b64encode((CASE / f"source_{i}.png").read_bytes()).decode()
    return request


VALID_SCENE = valid_scene()


@schemathesis.hook
def flatmap_body(ctx, body):
    operation = ctx.operation
    is_json_scene = isinstance(body, dict) and "request" not in body and not any(k.startswith("source_") for k in body)
    if operation is None or operation.method.upper() != "POST" or operation.path != "/v1/scenes" or not is_json_scene:
        return st.just(body)
    return st.sampled_from([body, VALID_SCENE])
