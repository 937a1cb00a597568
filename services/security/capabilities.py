"""``Can``: what a role may do on the router (publish, subscribe, serve, ask, declare tokens, watch), each as the
(flow, message) pairs the router must let through. Its own module, so the access-control rules (``acl.py``) and the
identities (``identities.py``) both import it without a circle."""

from __future__ import annotations

import enum


class Can(enum.Enum):
    """A capability, and the (flow, message) pairs it needs on the router."""

    PUBLISH = (("ingress", "put"), ("egress", "declare_subscriber"))
    SUBSCRIBE = (("ingress", "declare_subscriber"), ("egress", "put"))
    SERVE = (("ingress", "declare_queryable"), ("egress", "query"), ("ingress", "reply"))
    ASK = (("ingress", "query"), ("egress", "reply"), ("egress", "declare_queryable"))
    TOKEN = (("ingress", "liveliness_token"),)
    WATCH = (
        ("ingress", "declare_liveliness_subscriber"),
        ("ingress", "liveliness_query"),
        ("egress", "liveliness_token"),
    )
    PUT = (("ingress", "put"),)  # PUBLISH in two halves, when the keys differ
    SEE_SUBSCRIBERS = (("egress", "declare_subscriber"),)
