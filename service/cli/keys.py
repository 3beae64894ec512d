"""`posemetry keys`: API keys for operators, straight on the database (no running API or admin key needed).

This is the recovery path too: whoever can reach the database can always create a new admin key. Tokens are
printed once, alone on stdout (so `TOKEN=$(posemetry keys create ...)` works); everything else goes to stderr.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer
from rich.console import Console
from rich.table import Table

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

keys_app = typer.Typer(
    help="API keys: create (admin ones too, for recovery), list and revoke them, directly on the database.",
    no_args_is_help=True,
)

UrlOption = Annotated[
    str | None,
    typer.Option(
        help="Database URL (default: POSEMETRY_DATABASE_URL, else the SQLite file in POSEMETRY_DATA_DIR).",
        show_default=False,
    ),
]
PIPED_WIDTH = 200
_DURATION = re.compile(r"(\d+(?:\.\d+)?)([smhd])")
_UNIT_S = {"s": 1, "m": 60, "h": 3600, "d": 86400}
T = TypeVar("T")


def parse_duration(text: str) -> timedelta:
    """`90d`, `12h`, `30m`, `45s` as a timedelta (ValueError otherwise)."""
    match = _DURATION.fullmatch(text.strip())
    if match is None or float(match.group(1)) <= 0:
        raise ValueError(f"{text!r} is not a positive duration such as 90d, 12h, 30m or 45s")
    return timedelta(seconds=float(match.group(1)) * _UNIT_S[match.group(2)])


@contextmanager
def _session(url: str | None) -> Iterator[Session]:
    from service.settings import get_settings
    from service.store import make_engine, make_session_factory

    settings = get_settings()
    engine = make_engine(url or settings.database_url, busy_timeout_s=settings.database_busy_timeout_s)
    try:
        with make_session_factory(engine)() as session:
            yield session
    finally:
        engine.dispose()


def _run(url: str | None, work: Callable[[Session], T]) -> T:
    """`work` in a session; database errors become one red line and exit 1 (a password in the URL is not shown)."""
    from sqlalchemy.exc import SQLAlchemyError

    try:
        with _session(url) as session:
            return work(session)
    except (SQLAlchemyError, ValueError) as exc:
        hint = " (is the schema migrated? run `posemetry db upgrade`)" if "api_keys" in str(exc) else ""
        Console(stderr=True).print(f"[red]keys: {type(exc).__name__}: {str(exc).splitlines()[0]}{hint}[/red]")
        raise typer.Exit(1) from None


@keys_app.command("create")
def create(
    name: Annotated[str, typer.Option("--name", help="Who or what holds the key.")],
    admin: Annotated[bool, typer.Option("--admin", help="An admin key (manages keys; never camera-limited).")] = False,
    camera: Annotated[
        list[str] | None, typer.Option("--camera", help="Limit the key to this camera id (repeatable).")
    ] = None,
    expires_in: Annotated[
        str | None, typer.Option(help="Lifetime such as 90d, 12h or 30m (default: never expires).")
    ] = None,
    url: UrlOption = None,
) -> None:
    """Create a key and print its token once (only its hash is stored)."""
    from service.keys.schemas import KeyCreate
    from service.keys.service import CREATED_BY_CLI, issue_key

    try:
        expires_at = None if expires_in is None else datetime.now(UTC) + parse_duration(expires_in)
        request = KeyCreate(name=name, admin=admin, cameras=camera or None, expires_at=expires_at)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None

    def work(session: Session) -> tuple[str, str]:
        issued = issue_key(
            session,
            name=request.name,
            admin=request.admin,
            cameras=request.cameras,
            expires_at=request.expires_at,
            created_by=CREATED_BY_CLI,
        )
        session.commit()
        return issued.key.id, issued.token

    key_id, token = _run(url, work)
    scope = "admin" if admin else ("cameras " + ", ".join(sorted(set(camera))) if camera else "every camera")
    until = f", expires {expires_at.isoformat(timespec='seconds')}" if expires_at else ""
    Console(stderr=True).print(
        f"created API key {key_id} ({name}; {scope}{until}). The token below is shown only now; store it:",
        highlight=False,
    )
    typer.echo(token)


@keys_app.command("list")
def list_command(
    include_revoked: Annotated[bool, typer.Option("--all", help="Also list revoked keys.")] = False,
    url: UrlOption = None,
) -> None:
    """List keys (never their tokens): scope, creation, last use, expiry and revocation."""
    from service.keys import repository as stored_keys

    def work(session: Session) -> list[list[str]]:
        rows = []
        after = None
        while True:
            page = stored_keys.list_keys(session, limit=1000, after=after, include_revoked=include_revoked)
            rows += [_row(key) for key in page]
            if len(page) < 1000:
                return rows
            after = page[-1].id

    rows = _run(url, work)
    table = Table(title=f"{len(rows)} API keys", title_justify="left")
    for column in ("id", "name", "scope", "created", "last used", "expires", "revoked"):
        table.add_column(column, no_wrap=column == "id")
    for row in rows:
        table.add_row(*row)
    console = Console()
    if not console.is_terminal:
        console = Console(width=PIPED_WIDTH)  # piped output would be cut at 80 columns, wrapping names and dates
    console.print(table)


def _when(value: datetime | None) -> str:
    return "-" if value is None else value.strftime("%Y-%m-%d %H:%M:%S")


def _row(key: object) -> list[str]:
    from service.store.models import ApiKey

    assert isinstance(key, ApiKey)
    scope = "admin" if key.admin else ("every camera" if key.cameras is None else ", ".join(key.cameras))
    return [
        key.id,
        key.name,
        scope,
        _when(key.created_at),
        _when(key.last_used_at),
        _when(key.expires_at),
        _when(key.revoked_at),
    ]


@keys_app.command("revoke")
def revoke(
    key_id: Annotated[str, typer.Argument(help="The key's id (see `posemetry keys list`).")], url: UrlOption = None
) -> None:
    """Revoke a key: running API processes refuse it within POSEMETRY_API_KEY_CACHE_TTL_S."""
    from service.keys import repository as stored_keys
    from service.settings import get_settings

    def work(session: Session) -> bool:
        key = stored_keys.revoke_key(session, key_id)
        session.commit()
        return key is not None

    if not _run(url, work):
        Console(stderr=True).print(f"[red]no API key {key_id!r}[/red]", highlight=False)
        raise typer.Exit(1)
    ttl_s = get_settings().api_key_cache_ttl_s
    Console(stderr=True).print(
        f"revoked API key {key_id}; running API processes refuse it within {ttl_s:g} s", highlight=False
    )


def announce_first_admin_key(console: Console) -> None:
    """`posemetry serve`: with no POSEMETRY_ADMIN_KEY and no admin key ever stored, make one and print it, once.

    Once any admin key is stored this prints nothing, on every later start: the token cannot be recovered, and
    `posemetry keys create --admin` is the way to another one.
    """
    from service.keys.service import first_admin_key
    from service.settings import get_settings

    if get_settings().admin_key is not None:
        return
    with _session(None) as session:
        issued = first_admin_key(session)
    if issued is None:
        return
    rule = "-" * 78
    console.print(
        f"{rule}\nFirst admin API key, shown this once (only its hash is stored):\n\n    {issued.token}\n\n"
        "Send it as `Authorization: Bearer <key>`; admins create the other keys with POST /v1/keys.\n"
        "Lost it? `posemetry keys create --admin --name NAME` makes another.\n"
        f"{rule}",
        highlight=False,
        markup=False,
        soft_wrap=True,
    )


def warn_without_admin_key(console: Console) -> None:
    """`posemetry api`: say how to get an admin key when there is none (best effort: never stops the API)."""
    from sqlalchemy.exc import SQLAlchemyError

    from service.keys import repository as stored_keys
    from service.settings import get_settings

    if get_settings().admin_key is not None:
        return
    try:
        with _session(None) as session:
            if stored_keys.admin_key_ever_stored(session):
                return
    except SQLAlchemyError:
        return
    console.print(
        "[yellow]no admin API key: set POSEMETRY_ADMIN_KEY, or create one with "
        "`posemetry keys create --admin --name NAME`[/yellow]",
        highlight=False,
    )
