"""The test ledger: every flight of a test-block seed (`cefc_mj.seeds.TEST`), recorded once, in order.

A test batch is worth something only while no choice has looked at it. The ledger says which flights
have: one JSON object per line of `eval/test_ledger.jsonl` in the checkout, appended and never
rewritten. `cefc-eval` appends a flight record by itself whenever a game table (table5/6/7, the
SITL-M game), Table VIII or a single run flies games of a declared test batch
(`cefc_mj.seeds.TEST_BATCHES`) and says so in one line; a flight of other test-block seeds is not
recorded, and says that in one line. Before such a flight starts, the ledger it would be recorded in
is read and checked as every reader checks it (`read_ledger`): a damaged ledger (a line that is not a
record, torn lines included) is refused with one line naming the line, and nothing flies; the
writer checks it again under its lock before it appends. A later line can mark a flight as having
informed a change (`python -m cefc_mj.eval.ledger mark ID "what changed"`). A report flown on games
that an earlier flight informed a change with is tainted (`tainting_flights`; tests/test_test_ledger.py
holds every shipped report to that rule).

Where it writes (`ledger_path`):

- `CEFC_TEST_LEDGER=PATH`, when set: that file (tests and experiments, so they never dirty the
  repository);
- else, in a checkout: the repository's `eval/test_ledger.jsonl`;
- else (an installed wheel, no checkout): nowhere. Recording is skipped with one line on stderr, as it
  is when the file cannot be written; the flight itself goes on.

Appends are atomic: one `write` of one line on a file opened with O_APPEND, under an exclusive
`flock`, then fsync.

    python -m cefc_mj.eval.ledger                      # every flight, one line each
    python -m cefc_mj.eval.ledger mark ID "CHANGE"     # mark flight ID as having informed CHANGE
"""

from __future__ import annotations

import datetime
import fcntl
import hashlib
import json
import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

from cefc_mj import paths, seeds as seed_blocks
from cefc_mj.errors import CefcError, ConfigError, OneLineParser
from cefc_mj.provenance import display_path

ENV_VAR = "CEFC_TEST_LEDGER"
"""Environment variable naming the ledger file in place of the checkout's."""
LEDGER_NAME = "test_ledger.jsonl"
FLIGHT, MARK = "flight", "mark"
"""The two kinds of line: a flight, and a later mark that a flight informed a change."""


@dataclass(frozen=True)
class Flight:
    """One flight of test-block seeds: what flew, from which code, and whether it informed a change."""

    id: str
    """Unique within the ledger: protocol, first seed, date and a digest of the record."""
    protocol: str
    """table5, table6, table7, table5-sitl-m, table8 or single (`cefc_mj.seeds.PROTOCOL_FAMILY`)."""
    seed: int
    """--seed: the batch seed (table5-7) or the first of one seed per game."""
    episodes: int
    """Games in the batch, or seeds flown (seed .. seed + episodes - 1)."""
    command: str
    """The command line as run."""
    commit: str | None
    """git HEAD of the checkout that flew it (None when unknown)."""
    code_version: str | None
    """The package's source digest (`provenance.code_version`), None when unknown."""
    date: str
    """When it was recorded: an ISO date or date-time, UTC."""
    informed_change: bool = False
    """Whether its numbers led to a change (of code, policy, adversary, protocol or study size)."""
    change: str | None = None
    """What it informed, where informed_change."""
    outputs: tuple[str, ...] = ()
    """The report files it wrote (as given on the command line)."""
    note: str | None = None
    """Anything else (backfilled entries: where the numbers are documented)."""
    source: str = "cefc-eval"
    """"cefc-eval" (recorded by the run itself) or "backfill" (reconstructed from the repository)."""

    @property
    def family(self) -> str:
        """The games its seeds draw (`cefc_mj.seeds.PROTOCOL_FAMILY`)."""
        return seed_blocks.PROTOCOL_FAMILY[self.protocol]

    @property
    def seeds(self) -> frozenset[int]:
        """The seeds it touched: the batch seed, or one per game."""
        if self.protocol in seed_blocks.BATCH_SEEDED:
            return frozenset({self.seed})
        return frozenset(range(self.seed, self.seed + self.episodes))

    def overlaps(self, other: Flight) -> bool:
        """Whether the two flights flew some of the same games (same family, a seed in common)."""
        return self.family == other.family and bool(self.seeds & other.seeds)

    def to_json(self) -> dict:
        return {"kind": FLIGHT, **asdict(self), "outputs": list(self.outputs)}


@dataclass(frozen=True)
class Ledger:
    """The flights of a ledger file in order, with the marks applied."""

    path: Path | None
    """The file read (None: none exists)."""
    flights: list[Flight] = field(default_factory=list)
    """Every flight, in the order recorded."""

    def find(self, flight_id: str) -> Flight:
        for flight in self.flights:
            if flight.id == flight_id:
                return flight
        raise ConfigError(f"test ledger {self.path}: no flight {flight_id!r}")


def ledger_path() -> tuple[Path | None, str]:
    """(the ledger file, where it comes from) or (None, why nothing is recorded)."""
    given = os.environ.get(ENV_VAR)
    if given:
        return Path(given).expanduser(), ENV_VAR
    if paths.CHECKOUT_ROOT is not None:
        return paths.CHECKOUT_ROOT / "eval" / LEDGER_NAME, "checkout"
    return None, f"no checkout (an installed package); set {ENV_VAR}=PATH to record"


def _flight_from(record: dict, where: str) -> Flight:
    try:
        record = {k: v for k, v in record.items() if k != "kind"}
        record["outputs"] = tuple(record.get("outputs", ()))
        flight = Flight(**record)
    except TypeError as e:
        raise ConfigError(f"{where}: not a flight record ({e})") from None
    kinds = {"id": str, "protocol": str, "seed": int, "episodes": int, "command": str, "date": str}
    wrong = [name for name, kind in kinds.items() if not isinstance(getattr(flight, name), kind)]
    if wrong or isinstance(flight.seed, bool) or isinstance(flight.episodes, bool):
        raise ConfigError(f"{where}: not a flight record ({(wrong or ['seed'])[0]} of the wrong type)")
    if flight.protocol not in seed_blocks.PROTOCOL_FAMILY:
        raise ConfigError(
            f"{where}: protocol {flight.protocol!r} is not one of {', '.join(seed_blocks.PROTOCOL_FAMILY)}"
        )
    return flight


def read_ledger(path: Path | None = None) -> Ledger:
    """The flights of `path` (default `ledger_path()`), marks applied; an empty ledger where there is
    no file. ConfigError (one line, with the line number) for a line that is not a record, a torn
    last line included, and for a ledger that cannot be read: the one check every reader and writer
    of the ledger makes."""
    if path is None:
        path, _ = ledger_path()
    if path is None or not Path(path).exists():
        return Ledger(path)
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise ConfigError(f"test ledger {path}: cannot be read ({e.strerror or e})") from None
    return Ledger(Path(path), _parse(Path(path), data))


def _parse(path: Path, data: bytes) -> list[Flight]:
    """The flights of a ledger file's bytes (see read_ledger)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise ConfigError(f"test ledger {path}:{line}: not UTF-8 text; repair or remove that line") from None
    flights: dict[str, Flight] = {}
    for number, line in enumerate(text.split("\n"), 1):
        where = f"test ledger {path}:{number}"
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except (json.JSONDecodeError, RecursionError) as e:
            reason = e.msg if isinstance(e, json.JSONDecodeError) else "nested too deeply"
            raise ConfigError(f"{where}: not JSON ({reason}); repair or remove that line") from None
        kind = record.get("kind") if isinstance(record, dict) else None
        if kind == FLIGHT:
            flight = _flight_from(record, where)
            if flight.id in flights:
                raise ConfigError(f"{where}: flight {flight.id!r} recorded twice")
            flights[flight.id] = flight
        elif kind == MARK:
            target = flights.get(record.get("flight")) if isinstance(record.get("flight"), str) else None
            if target is None:
                raise ConfigError(f"{where}: marks flight {record.get('flight')!r}, which no earlier line records")
            flights[target.id] = Flight(
                **{**asdict(target), "informed_change": True, "change": record.get("change"), "outputs": target.outputs}
            )
        else:
            raise ConfigError(f"{where}: kind {kind!r} is neither {FLIGHT!r} nor {MARK!r}")
    return list(flights.values())


def flights(protocol: str | None = None, seed: int | None = None, path: Path | None = None) -> list[Flight]:
    """The recorded flights (of `protocol`, and touching `seed`, where given), in order."""
    return [
        f
        for f in read_ledger(path).flights
        if (protocol is None or f.protocol == protocol) and (seed is None or seed in f.seeds)
    ]


def tainting_flights(flight: Flight, ledger: list[Flight]) -> list[Flight]:
    """The flights recorded before `flight` (which must be in `ledger`) that flew some of its games
    and informed a change: a report from `flight` is tainted where there is any."""
    index = next((i for i, f in enumerate(ledger) if f.id == flight.id), None)
    if index is None:
        raise ConfigError(f"flight {flight.id!r} is not in the ledger")
    return [f for f in ledger[:index] if f.informed_change and f.overlaps(flight)]


def _append(path: Path, record: dict) -> None:
    """Append one JSON line atomically (O_APPEND, flock, one write, fsync), after checking the ledger
    as `read_ledger` does, under the lock (ConfigError for a damaged ledger: nothing is appended)."""
    line = (json.dumps(record, sort_keys=False) + "\n").encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        chunks = []
        while chunk := os.pread(fd, 1 << 20, sum(map(len, chunks))):
            chunks.append(chunk)
        data = b"".join(chunks)
        _parse(path, data)
        if data and not data.endswith(b"\n"):
            raise ConfigError(f"test ledger {path}: its last line has no newline (torn); repair it before recording")
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _flight_id(protocol: str, seed: int, date: str, record: dict) -> str:
    digest = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:8]
    return f"{protocol}-s{seed}-{date[:10]}-{digest}"


def flight_seeds(protocol: str, seed: int, episodes: int) -> range:
    """The seeds a flight touches: its batch seed (table5-7), or one per game (the others)."""
    return range(seed, seed + 1) if protocol in seed_blocks.BATCH_SEEDED else range(seed, seed + episodes)


def declared_batches(protocol: str, seed: int, episodes: int) -> list[seed_blocks.TestBatch]:
    """The declared test batches (`cefc_mj.seeds.TEST_BATCHES`) whose games a flight flies: same
    family of games, a seed in common."""
    family, seeds = seed_blocks.PROTOCOL_FAMILY[protocol], flight_seeds(protocol, seed, episodes)
    return [
        b
        for b in seed_blocks.TEST_BATCHES
        if b.family == family and b.first < seeds.stop and seeds.start < b.first + b.count
    ]


def check_before_flight(protocol: str, seed: int, episodes: int) -> None:
    """What `cefc-eval` calls before a flight starts: where the flight would be recorded (it flies a
    declared test batch), the ledger is read and checked (`read_ledger`); ConfigError with one line for
    a damaged one, so that nothing flies."""
    if declared_batches(protocol, seed, episodes):
        path, _ = ledger_path()
        if path is not None:
            read_ledger(path)


def touches_test_block(protocol: str, seed: int, episodes: int) -> bool:
    """Whether a flight of `protocol` from `seed` with `episodes` flies any seed of the test block."""
    if protocol in seed_blocks.BATCH_SEEDED:
        return seed in seed_blocks.TEST
    return any(s in seed_blocks.TEST for s in range(seed, seed + episodes))


def record_flight(
    protocol: str,
    seed: int,
    episodes: int,
    command: str,
    provenance: dict | None = None,
    outputs=(),
    informed_change: bool = False,
    change: str | None = None,
    note: str | None = None,
    date: str | None = None,
    source: str = "cefc-eval",
    path: Path | None = None,
) -> Flight | None:
    """Append a flight of test-block seeds to the ledger (path: default `ledger_path()`) and return it;
    None, with one line on stderr saying why, where nothing could be recorded (no checkout and no
    CEFC_TEST_LEDGER, or the file cannot be written). provenance: the run's (`git_commit`,
    `code_version`). A flight that flies no declared test batch is refused (ConfigError): only the
    declared test batches are ledgered. ConfigError, nothing appended, for a damaged ledger."""
    if protocol not in seed_blocks.PROTOCOL_FAMILY:
        raise ConfigError(f"protocol {protocol!r}: must be one of {', '.join(seed_blocks.PROTOCOL_FAMILY)}")
    if not touches_test_block(protocol, seed, episodes):
        raise ConfigError(f"{protocol} from seed {seed} ({episodes} episodes) flies no seed of the test block")
    if not declared_batches(protocol, seed, episodes):
        raise ConfigError(
            f"{protocol} from seed {seed} ({episodes} episodes) flies no declared test batch "
            "(cefc_mj.seeds.TEST_BATCHES)"
        )
    where = "given"
    if path is None:
        path, where = ledger_path()
    if path is None:
        print(f"test ledger: this flight of test seeds is not recorded ({where})", file=sys.stderr)
        return None
    prov = provenance or {}
    date = date or _now()
    record = {
        "protocol": protocol,
        "seed": int(seed),
        "episodes": int(episodes),
        "command": command,
        "commit": prov.get("git_commit"),
        "code_version": prov.get("code_version"),
        "date": date,
        "informed_change": bool(informed_change),
        "change": change,
        "outputs": [str(o) for o in outputs],
        "note": note,
        "source": source,
    }
    flight = _flight_from({**record, "id": _flight_id(protocol, seed, date, record)}, "record")
    read_ledger(Path(path))  # a damaged or unreadable ledger: ConfigError, as every reader says it
    try:
        _append(Path(path), flight.to_json())
    except OSError as e:
        print(f"test ledger: this flight of test seeds is not recorded ({path}: {e.strerror or e})", file=sys.stderr)
        return None
    return flight


def record_if_test(protocol: str, seed: int, episodes: int, command: str, provenance: dict | None, outputs=()):
    """What cefc-eval calls once a flight's numbers are out: `record_flight` where the flight flies a
    declared test batch, saying so in one line; one line saying it is not recorded where it flies
    other seeds of the test block; nothing for seeds outside the test block. Returns the flight or None."""
    if not touches_test_block(protocol, seed, episodes):
        return None
    batches = declared_batches(protocol, seed, episodes)
    if not batches:
        seeds = flight_seeds(protocol, seed, episodes)
        shown = f"seed {seed} is" if len(seeds) == 1 else f"seeds {seeds.start}..{seeds.stop - 1} are"
        print(
            f"test ledger: not recorded: {shown} in the test block but in no declared test batch "
            "(cefc_mj.seeds.TEST_BATCHES)"
        )
        return None
    flight = record_flight(protocol, seed, episodes, command, provenance, [str(o) for o in outputs if o is not None])
    if flight is not None:
        names = ", ".join(repr(b.name) for b in batches)
        print(f"test ledger: flight {flight.id} of test batch {names} recorded in {display_path(ledger_path()[0])}")
    return flight


def mark_informed_change(flight_id: str, change: str, path: Path | None = None) -> Flight:
    """Append a line marking flight `flight_id` as having informed `change`; returns the marked flight.
    ConfigError where there is no ledger or no such flight."""
    if path is None:
        path, where = ledger_path()
        if path is None:
            raise ConfigError(f"no test ledger ({where})")
    if not change.strip():
        raise ConfigError("the change: say what the flight's numbers led to")
    read_ledger(path).find(flight_id)
    _append(Path(path), {"kind": MARK, "flight": flight_id, "change": change, "date": _now()})
    return read_ledger(path).find(flight_id)


def describe(flight: Flight) -> str:
    """One line: id, protocol, seeds, date, commit, and the change it informed."""
    seeds_text = str(flight.seed) if len(flight.seeds) == 1 else f"{flight.seed}..{flight.seed + flight.episodes - 1}"
    commit = (flight.commit or "?")[:10]
    informed = f"; informed: {flight.change}" if flight.informed_change else ""
    return (
        f"{flight.id}  {flight.protocol} seeds {seeds_text} ({flight.family})  {flight.date[:10]}  {commit}{informed}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m cefc_mj.eval.ledger", description="The test ledger: list or mark flights.")
    sub = parser.add_subparsers(dest="action")
    sub.add_parser("list", help="every flight, one line each (the default)")
    mark = sub.add_parser("mark", help="mark a flight as having informed a change")
    mark.add_argument("flight", help="the flight's id (as `list` prints it)")
    mark.add_argument("change", help="what its numbers led to")
    args = parser.parse_args(argv)
    try:
        if args.action == "mark":
            print(describe(mark_informed_change(args.flight, args.change)))
            return 0
        ledger = read_ledger()
        print(f"test ledger: {ledger.path or ledger_path()[1]}, {len(ledger.flights)} flights")
        for flight in ledger.flights:
            print(describe(flight))
    except CefcError as e:
        print(f"{parser.prog}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
