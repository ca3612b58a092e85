"""Who may do what on the bus: the per-role policy, as pure data and config building.

`ROLES` is the table of what each role may publish, subscribe, query, answer and
watch on the key space. The router's ACL (`acl_config`), docs/deploy.md's permission
table (`permissions_markdown`) and the tests all read it, so they cannot disagree. It
is apart from the TLS settings and the log parsing (shared/net/security.py) so the
policy reads as one table and changes on its own. Nothing here imports zenoh.

Identity: a session's user name is its service id (`actor0`, `counter`, `api`, `cli`,
`router-a`); its role is that name, or the name's leading role word followed by a
digit or `-` (`actor-h2-0` is an actor). A user whose name names no role is refused
when the router starts.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

NS = "macb"


class SecurityError(ValueError):
    """A security setting is missing, contradictory or names a file that cannot be used."""


# ---------------------------------------------------------------- the permission table
@dataclass(frozen=True)
class Grant:
    """One thing a role may do on a key expression (`{id}`: the user's own name).

    Actions, and the Zenoh messages each allows (ingress: from the session into the
    router; egress: from the router to the session):
      pub    put                                   ingress
      sub    declare_subscriber ingress, put       egress
      serve  declare_queryable ingress, query egress, reply ingress
      query  query ingress, reply egress
      token  liveliness_token                      ingress
      watch  declare_liveliness_subscriber and liveliness_query ingress, liveliness_token egress
      all    every message, both ways (routers peering with routers)
    """

    action: str
    key: str
    why: str = ""
    # serve only: the key expressions queries may name to reach it (a querier's
    # wildcard, `macb/info/*/*`, is checked as it is, not as the queryable's key)
    asked_as: str | None = None


ACTIONS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "pub": (("ingress", ("put", "delete")),),
    "sub": (("ingress", ("declare_subscriber",)), ("egress", ("put", "delete"))),
    "serve": (
        ("ingress", ("declare_queryable", "reply")),
        ("egress", ("query",)),
    ),
    "query": (("ingress", ("query",)), ("egress", ("reply",))),
    "token": (("ingress", ("liveliness_token",)),),
    "watch": (
        ("ingress", ("declare_liveliness_subscriber", "liveliness_query")),
        ("egress", ("liveliness_token",)),
    ),
    "all": (
        (
            "ingress",
            (
                "put",
                "delete",
                "declare_subscriber",
                "query",
                "reply",
                "declare_queryable",
                "liveliness_token",
                "liveliness_query",
                "declare_liveliness_subscriber",
            ),
        ),
        (
            "egress",
            (
                "put",
                "delete",
                "declare_subscriber",
                "query",
                "reply",
                "declare_queryable",
                "liveliness_token",
                "liveliness_query",
                "declare_liveliness_subscriber",
            ),
        ),
    ),
}

# What any service (counter, learner, actor, evaluator) does: follow run control, say it
# is alive, answer `macb ps`, report its status and its stats.
_SERVICE = (
    Grant("sub", f"{NS}/control/*", "receive start and stop"),
    Grant("token", f"{NS}/live/{{role}}/{{id}}", "its own liveliness token"),
    Grant("watch", f"{NS}/live/*/*", "see which services are alive"),
    Grant(
        "serve", f"{NS}/info/{{role}}/{{id}}", "answer `macb ps` and the scheduler", f"{NS}/info/**"
    ),
    Grant("pub", f"{NS}/run/*/status/{{id}}", "its own status"),
    Grant("sub", f"{NS}/run/*/status/*", "follow the run's learner"),
)
# Observers of runs (the API and the CLI): read metrics and status, find services.
_OBSERVER = (
    Grant("pub", f"{NS}/control/*", "start and stop runs"),
    Grant("sub", f"{NS}/run/*/metrics/**", "live metrics"),
    Grant("sub", f"{NS}/run/*/status/*", "run status"),
    Grant("query", f"{NS}/info/*/*", "find services (`macb ps`, assignment)"),
    Grant("query", f"{NS}/router/*", "the routers' denial counts"),
    Grant("watch", f"{NS}/live/*/*", "see which services are alive"),
)

ROLES: dict[str, tuple[Grant, ...]] = {
    "actor": (
        *_SERVICE,
        Grant("pub", f"{NS}/run/*/transitions/{{id}}", "its own transitions only"),
        Grant("pub", f"{NS}/run/*/metrics/actor/{{id}}", "its stats"),
        Grant("sub", f"{NS}/run/*/weights/*", "the latest weights"),
        Grant("sub", f"{NS}/run/*/ack/*", "the counter's and learner's acks"),
        Grant("pub", f"{NS}/run/*/act/{{id}}", "lockstep: its own act requests"),
        Grant("sub", f"{NS}/run/*/action/{{id}}", "lockstep: the actions for it"),
    ),
    "learner": (
        *_SERVICE,
        Grant("sub", f"{NS}/run/*/transitions/*", "every actor's transitions"),
        Grant("sub", f"{NS}/run/*/ack/*", "the counter's acks"),
        Grant("sub", f"{NS}/run/*/act/*", "lockstep: the actors' act requests"),
        Grant("pub", f"{NS}/run/*/action/*", "lockstep: the policy's actions"),
        Grant("sub", f"{NS}/run/*/metrics/eval", "the evaluator's points"),
        Grant("pub", f"{NS}/run/*/weights/*", "weights"),
        Grant("pub", f"{NS}/run/*/ack/{{id}}", "its acks (credits)"),
        Grant("pub", f"{NS}/run/*/metrics/learner", "its stats"),
        Grant("pub", f"{NS}/run/*/metrics/provenance", "what it runs on (once per start)"),
        Grant("query", f"{NS}/run/*/bonus", "bonus queries"),
        Grant("query", f"{NS}/info/counter/*", "the counter's state"),
    ),
    "counter": (
        *_SERVICE,
        Grant("sub", f"{NS}/run/*/transitions/*", "every actor's transitions"),
        Grant("serve", f"{NS}/run/*/bonus", "answer bonus queries"),
        Grant("pub", f"{NS}/run/*/ack/{{id}}", "its acks"),
        Grant("pub", f"{NS}/run/*/metrics/counter", "its stats"),
    ),
    "evaluator": (
        *_SERVICE,
        Grant("sub", f"{NS}/run/*/weights/eval", "weights marked for evaluation"),
        Grant("serve", f"{NS}/run/*/history/eval", "every row so far (API gap filling)"),
        Grant("pub", f"{NS}/run/*/metrics/eval", "the evaluation points"),
    ),
    "api": (
        *_OBSERVER,
        Grant("token", f"{NS}/live/api/{{id}}", "its own liveliness token"),
        Grant("serve", f"{NS}/info/api/{{id}}", "answer `macb ps`", f"{NS}/info/**"),
        Grant("query", f"{NS}/run/*/history/eval", "fill gaps after a restart"),
    ),
    "cli": _OBSERVER,
    "router": (Grant("all", "**", "routers forward everything between them"),),
}

# Every authenticated session may see declarations (who subscribes or answers where):
# publishers need them to know a subscriber exists. Values never pass by this rule.
SEE_DECLARATIONS = (
    ("egress", ("declare_subscriber", "declare_queryable", "liveliness_token")),
    f"{NS}/**",
)


def role_of(user: str) -> str:
    """A user's role: its name, or its leading role word before a digit or `-`. Names
    are letters, digits and `-_.` only: a name is part of the user's key expressions
    (`transitions/{id}`), so `*`, `/` or `$` in it would widen them."""
    if user in ROLES:
        return user
    m = re.fullmatch(r"([a-z]+)[-0-9][A-Za-z0-9_.-]*", user)
    if m and m.group(1) in ROLES:
        return m.group(1)
    raise SecurityError(
        f"user {user!r} names no role: a user is named after its role "
        f"({', '.join(ROLES)}), e.g. actor0, actor-h2-0, router-a"
    )


def _messages(user: str) -> list[tuple[str, tuple[str, ...], str]]:
    """(flow, messages, key expression) of everything `user` may do."""
    role = role_of(user)
    parts = []
    for g in ROLES[role]:
        key = g.key.format(id=user, role=role)
        for flow, msgs in ACTIONS[g.action]:
            asked = g.asked_as if g.action == "serve" and flow == "egress" else None
            parts.append((flow, msgs, asked if asked is not None else key))
    parts.append((*SEE_DECLARATIONS[0], SEE_DECLARATIONS[1]))
    return parts


def acl_config(users: list[str]) -> dict[str, Any]:
    """Zenoh's `access_control` section for these users: deny by default, one subject
    per user (so a message is checked against exactly one subject), its role's grants."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for user in sorted(set(users)):
        ids: list[str] = []
        parts = _messages(user)
        merged: dict[tuple[str, str], list[str]] = {}  # (flow, message) -> keys
        for flow, msgs, key in parts:
            for msg in msgs:
                keys = merged.setdefault((flow, msg), [])
                if key not in keys:
                    keys.append(key)
        for n, ((flow, msg), keys) in enumerate(sorted(merged.items())):
            rid = f"{user}.{n}"
            rules.append(
                {
                    "id": rid,
                    "messages": [msg],
                    "flows": [flow],
                    "permission": "allow",
                    "key_exprs": keys,
                }
            )
            ids.append(rid)
        subjects.append({"id": f"user.{user}", "usernames": [user]})
        names = [f"user.{user}"]
        if role_of(user) == "router":
            # A router that connects to another signs in there with its user name, but
            # the one it connects to proves itself only by its TLS certificate: routers
            # are also known by their certificate's common name (signed by the CA).
            subjects.append({"id": f"cert.{user}", "cert_common_names": [user]})
            names.append(f"cert.{user}")
        policies.append({"id": f"policy.{user}", "rules": ids, "subjects": names})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def permissions_markdown() -> str:
    """The permission table of docs/deploy.md, rendered from `ROLES` (a test keeps the
    doc equal to this, so the doc says what the ACL enforces). `{id}` is the user."""
    columns = (
        ("pub", "puts on"),
        ("sub", "subscribes to"),
        ("query", "queries"),
        ("serve", "answers queries on"),
        ("token", "liveliness token"),
        ("watch", "watches liveliness"),
    )
    rows = ["| role | " + " | ".join(title for _, title in columns) + " |"]
    rows.append("|---" * (len(columns) + 1) + "|")
    for role, grants in ROLES.items():
        if any(g.action == "all" for g in grants):
            rows.append(f"| {role} | everything, both ways (`**`) |" + " |" * (len(columns) - 1))
            continue
        cells = []
        for action, _ in columns:
            keys = [f"`{g.key.replace('{role}', role)}`" for g in grants if g.action == action]
            cells.append(", ".join(keys) or "-")
        rows.append(f"| {role} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"
