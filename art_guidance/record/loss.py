"""What a bag folder lost: the messages read compared with what `metadata.yaml` counts.

The recorder rewrites `metadata.yaml` after every solve is on disk, so in a finished bag, or one
whose recorder was killed, its per-topic and per-file counts are those of the data. It may lag
by the last solve (a kill between the write and the rewrite) or be absent; more messages read
than counted is reported as such, never as loss. Where it is absent, the damaged chunks' own
message index counts are all that is known. Damage that cost no message (`Damage.no_loss`: a
summary not needed, a damaged copy of a chunk read intact) counts for nothing, and a damaged
chunk counts only the messages it held that were read nowhere else. Solves are counted by their
SolveRecord.
"""
from __future__ import annotations

from pathlib import Path

import yaml

from art_guidance.files import load_yaml
from art_guidance.record.bag_metadata import METADATA_FILE
from art_guidance.record.recorder import PLAN_TYPE, SOLVE_RECORD_TYPE
from art_guidance.record.scan import Damage


def recorded_counts(directory: Path) -> tuple[dict | None, str]:
    """({"topics": {name: (type, count)}, "files": {path: count}, "state": str}, note) from
    the folder's metadata.yaml; None and why when it is absent or unreadable."""
    path = directory / METADATA_FILE
    try:
        info = load_yaml(path.read_text())["rosbag2_bagfile_information"]
        topics = {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"],
                                                int(t["message_count"]))
                  for t in info.get("topics_with_message_count") or []}
        files = {f["path"]: int(f["message_count"]) for f in info.get("files") or []}
        if not files:
            files = {p: -1 for p in info.get("relative_file_paths") or []}
        custom = info.get("custom_data") or {}
        state = str(custom.get("art_guidance.state", "unknown"))
        repair = custom.get("art_guidance.repair")
    except FileNotFoundError:
        return None, f"no {METADATA_FILE}: the loss is known only from the damaged chunks"
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        return None, (f"{METADATA_FILE} unreadable ({type(exc).__name__}: {exc}): the loss is "
                      "known only from the damaged chunks")
    total = sum(n for _, n in topics.values())
    dropped = int(custom.get("art_guidance.dropped_files", 0) or 0)
    retention = (f"; the retention cap dropped the {dropped} oldest file(s) "
                 f"({custom.get('art_guidance.dropped_messages', '?')} messages) by design"
                 if dropped else "")
    if repair:  # written by `bag reindex`: the loss it found is before these counts
        repair = (f"{METADATA_FILE} was rewritten by a repair ({repair}; "
                  f"{custom.get('art_guidance.lost_messages', '?')} message(s) lost then)")
    return ({"topics": topics, "files": files, "state": state, "repair": repair or ""},
            f"{METADATA_FILE} ({state}) counts {total} messages in {len(files)} file(s)"
            f"{retention}")


def _from_damage(damaged: list[Damage]) -> dict[str, int]:
    """Messages lost per topic per the damaged chunks' message index (not read elsewhere)."""
    by_topic: dict[str, int] = {}
    for damage in damaged:
        for topic, n in damage.by_topic.items():
            by_topic[topic] = by_topic.get(topic, 0) + n
    return by_topic


def account(path: Path, read_topics: dict[str, int], read_files: dict[str, int],
            types: dict[str, str], damaged: list[Damage]) -> dict:
    """The loss of a bag folder (or of one file of it) as a JSON-ready dict.

    Args:
        path: the bag folder, or one .mcap file (then only its own count is compared).
        read_topics: messages read per topic; read_files: per file name.
        types: topic -> 'pkg/msg/Type' of what was read (metadata.yaml fills in the rest).
        damaged: the damage found while reading (its message index counts, where known);
            damage that lost nothing (`Damage.lost_data` False) is left out.

    Returns:
        {"messages": total lost or None (unknown), "solves": lost solves (SolveRecords or
        ManeuverPlans, the larger) or None, "complete": False where these are lower bounds (no
        metadata.yaml, a damaged chunk without message index), "by_topic", "by_type",
        "files": {name: lost}, "source", "metadata" (what metadata.yaml counts, or why it
        is not used), "notes" (metadata lagging the data, missing files, an earlier repair)}.
    """
    single = path.is_file()
    recorded, note = recorded_counts(path.parent if single else path)
    notes = [recorded["repair"]] if recorded is not None and recorded["repair"] else []
    damaged = [d for d in damaged if d.lost_data]
    by_topic = _from_damage(damaged)
    files: dict[str, int] = {}
    if recorded is not None:
        types = {**{t: ty for t, (ty, _) in recorded["topics"].items()}, **types}
        listed = recorded["files"]
        names = [path.name] if single else sorted(set(listed) | set(read_files))
        for name in names:
            got, want = read_files.get(name, 0), listed.get(name)
            if want is None:
                notes.append(f"{name} is not in {METADATA_FILE} yet ({got} messages read): "
                             "it lags the data")
            elif name not in read_files and not single:
                files[name] = max(want, 0)
                notes.append(f"{name} is listed in {METADATA_FILE} ({want} messages) but "
                             "missing")
            elif want >= 0 and got != want:
                files[name] = max(want - got, 0)
                if got > want:
                    notes.append(f"{name}: {got} messages read, {METADATA_FILE} counts {want}: "
                                 "it lags the data")
        if not single:
            # what a damaged chunk held on a channel defined nowhere that was read ("channel
            # <id>": its topic is unknown) is among the deficits of the topics counted here
            by_topic = {t: n for t, n in by_topic.items() if t in recorded["topics"]
                        or not t.startswith("channel ")}
            for topic, (_, want) in recorded["topics"].items():
                got = read_topics.get(topic, 0)
                if got > want:
                    notes.append(f"{topic}: {got} read, {METADATA_FILE} counts {want}: it "
                                 "lags the data")
                by_topic[topic] = max(by_topic.get(topic, 0), want - got)
    by_topic = {t: n for t, n in by_topic.items() if n > 0}
    by_type: dict[str, int] = {}
    for topic, n in by_topic.items():
        by_type[types.get(topic, "unknown")] = by_type.get(types.get(topic, "unknown"), 0) + n
    known = recorded is not None or all(d.messages is not None for d in damaged)
    total = max(sum(by_topic.values()), sum(files.values()))
    solves = max(by_type.get(SOLVE_RECORD_TYPE, 0), by_type.get(PLAN_TYPE, 0))
    return {"messages": total if known or total else None,
            "solves": solves if known or solves else None, "complete": known,
            "by_topic": by_topic, "by_type": by_type,
            "files": {n: k for n, k in files.items() if k > 0},
            "source": METADATA_FILE if recorded is not None else "message index",
            "metadata": note, "notes": notes}


def describe(lost: dict) -> str:
    """One line: what was lost, per type."""
    if lost["messages"] is None:
        return "lost: unknown (no metadata.yaml and a damaged chunk without a message index)"
    if not lost["messages"]:
        return ("lost: nothing (every message metadata.yaml counts was read)"
                if lost["source"] == METADATA_FILE else
                "lost: nothing found (no metadata.yaml to count against)")
    least = "" if lost["complete"] else "at least "
    kinds = ", ".join(f"{n} {t.split('/')[-1]}" for t, n in sorted(lost["by_type"].items()))
    where = "".join(f"; {n} from {f}" for f, n in sorted(lost["files"].items()))
    return (f"lost: {least}{lost['messages']} message(s), {lost['solves']} solve(s) ({kinds})"
            f"{where} (per {lost['source']})")
