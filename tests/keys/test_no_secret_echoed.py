"""No credential comes back in a response or goes into a log line, on any path where one is refused (issue 14).

Against a real `posemetry serve` with its JSON logs captured (debug level, every process): every way a key can be
sent wrongly or be no good (no `Bearer `, another scheme, malformed, unknown, a wrong secret, revoked, expired,
over-long, in the query or the path), for stored keys and for the admin key of POSEMETRY_ADMIN_KEY, and webhook
secrets refused in their bodies. A credential counts as echoed when an answer (headers or body) or a log line
shows any 10 consecutive characters of its secret, or a stored key's id with a secret character after it. The 401
for a key sent without `Bearer ` once echoed its first 20 characters (4 of a stored key's secret characters, 20 of
an admin key's).
"""

from __future__ import annotations

import base64
import json
import secrets
import shutil
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from tests.support.serving import Served, clean_environment, serve

WINDOW = 10


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Served, Path]]:
    data_dir = Path(tempfile.mkdtemp(prefix="pm-secrets-"))
    log = data_dir / "serve.log"
    admin_key = secrets.token_hex(32)  # as README suggests: `openssl rand -hex 32`
    env = clean_environment(admin_key=admin_key, log_format="json", log_level="debug")
    try:
        with serve(data_dir / "data", env, output=log) as app:
            yield app, log
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def _windows(secret: str) -> set[str]:
    return {secret[i : i + WINDOW] for i in range(len(secret) - WINDOW + 1)}


def _shows(text: str, token: str) -> bool:
    """Whether `text` shows any of the secret: 10 characters of it anywhere, or, for a stored key, its id followed
    by even one secret character (how the 401 for a key without `Bearer ` showed 4 of them)."""
    if token.startswith("pm_") and token[: len("pm_") + 12 + 2] in text:
        return True
    return bool(_windows(_secret_part(token)) & _windows(text))


def _secret_part(token: str) -> str:
    """What must never be shown: a stored key's part after its id (`pm_<id>_`), or all of another credential."""
    return token.split("_", 2)[2] if token.startswith("pm_") else token


def _exchange(app: Served, method: str, path: str, headers: dict[str, str], body: Any = None) -> tuple[int, str]:
    """(status, everything the client got back as text: headers and body)."""
    import urllib.error
    import urllib.request

    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(f"{app.base}{path}", data=data, method=method, headers=headers)
    if data is not None:
        request.add_header("content-type", "application/json")
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, str(response.headers) + response.read().decode(errors="replace")
    except urllib.error.HTTPError as exc:
        return exc.code, str(exc.headers) + exc.read().decode(errors="replace")


def test_no_auth_failure_echoes_a_credential_in_answers_or_logs(served: tuple[Served, Path]) -> None:
    app, log = served
    admin_key = app.api_key or ""
    status, created = app.http("POST", "/v1/keys", {"name": "valid", "cameras": ["lobby"]})
    assert status == 201
    valid = created["token"]
    revoked = app.http("POST", "/v1/keys", {"name": "revoked"})[1]
    assert app.http("DELETE", f"/v1/keys/{revoked['id']}")[0] == 200
    soon = (datetime.now(UTC) + timedelta(seconds=1)).isoformat()
    expiring = app.http("POST", "/v1/keys", {"name": "expiring", "expires_at": soon})[1]
    assert app.http("GET", "/v1/keys/current", token=expiring["token"])[0] == 200  # cached while still valid
    time.sleep(1.5)
    unknown = f"pm_{secrets.token_hex(6)}_{valid.split('_', 2)[2][::-1]}"
    wrong_secret = valid[:-8] + "AAAAAAAA"

    credentials = {
        "stored key": valid,
        "admin key": admin_key,
        "revoked key": revoked["token"],
        "expired key": expiring["token"],
        "unknown key": unknown,
        "wrong secret": wrong_secret,
    }
    sent: list[tuple[str, int]] = []

    def send(name: str, method: str, path: str, headers: dict[str, str], body: Any = None) -> None:
        status, answer = _exchange(app, method, path, headers, body)
        leaked = [what for what, token in credentials.items() if _shows(answer, token)]
        assert not leaked, f"{name}: {status} answer shows {leaked}: {answer[:400]}"
        sent.append((name, status))

    for what, token in credentials.items():
        for how, header in {
            "without Bearer": token,
            "Token scheme": f"Token {token}",
            "Basic scheme": "Basic " + base64.b64encode(f"user:{token}".encode()).decode(),
            "lower-case scheme glued on": f"bearer{token}",
            "malformed (one character more)": f"Bearer {token}x",
            "over-long (the key and 4 KB)": f"Bearer {token}{'A' * 4096}",
            "as sent": f"Bearer {token}",
        }.items():
            for method, path, body in (("GET", "/v1/cameras", None), ("POST", "/v1/cameras/lobby/keypoints", {})):
                send(f"{what} {how} {method}", method, path, {"Authorization": header}, body)
        send(f"{what} in the query", "GET", f"/v1/cameras?api_key={token}", {})
        send(f"{what} in the path", "GET", f"/v1/keys/{token}", {"Authorization": f"Bearer {admin_key}"})
        send(f"{what} in X-Request-ID", "GET", "/v1/cameras", {"X-Request-ID": token})
    send("a 64 KB key", "GET", "/v1/cameras", {"Authorization": f"Bearer {valid}{'B' * 65536}"})

    # Webhook secrets refused in their bodies: malformed, too short, or with a URL the SSRF policy refuses.
    admin = {"Authorization": f"Bearer {admin_key}"}
    good_secret = "whsec_" + base64.b64encode(secrets.token_bytes(32)).decode()
    for name, secret in {
        "webhook secret, bad base64": "whsec_" + secrets.token_urlsafe(40) + "!",
        "webhook secret, too short": "whsec_" + base64.b64encode(secrets.token_bytes(8)).decode(),
        "webhook secret, no prefix": base64.b64encode(secrets.token_bytes(32)).decode(),
        "webhook secret, refused url": good_secret,
    }.items():
        credentials[name] = secret
        send(name, "POST", "/v1/webhooks", admin, {"url": "http://127.0.0.1:9/hook", "secret": secret})
        nowhere = f"/v1/webhooks/{'0' * 8}-0000-0000-0000-{'0' * 12}/secret"
        send(f"{name} (rotation)", "POST", nowhere, admin, {"secret": secret})

    statuses = {status for _, status in sent}
    assert statuses <= {200, 400, 401, 403, 404, 422, 431}, sent
    assert sum(status == 401 for _, status in sent) >= 6 * 12
    app.stop()
    lines = log.read_text(errors="replace").splitlines()
    assert any('"logger": "posemetry.access"' in line for line in lines)  # the JSON logs were captured
    for what, token in credentials.items():
        shown = [line for line in lines if _shows(line, token)]
        assert not shown, f"{what} in the logs: {shown[:3]}"
    masked = [line for line in lines if "[redacted]" in line]
    assert masked, "the keys sent in paths were not masked (nor anything else)"
