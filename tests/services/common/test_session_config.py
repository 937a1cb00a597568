"""The Zenoh config every service builds (no session is opened here)."""

from __future__ import annotations

from services.common.zenoh_session import ZenohSettings, build_config, session_mode


def test_shared_memory_is_off_unless_a_config_file_says_otherwise(tmp_path):
    # with it on, each publishing process on the host left a 16 MB segment mapped in every subscriber (19 MB more
    # after each round of the soak's bombs); a user's own file decides for itself
    conf = build_config(ZenohSettings(mode="client", connect=("tcp/127.0.0.1:7447",), no_multicast_scouting=True))
    assert conf.get_json("transport/shared_memory/enabled") == "false"
    own = tmp_path / "z.json5"
    own.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert build_config(ZenohSettings(config=str(own))).get_json("transport/shared_memory/enabled") == "true"


def test_a_services_own_defaults_add_to_the_shared_ones():
    conf = build_config(ZenohSettings(), {"transport/link/rx/max_message_size": "8388608"})
    assert conf.get_json("transport/link/rx/max_message_size") == "8388608"
    assert conf.get_json("transport/shared_memory/enabled") == "false"


def test_the_session_mode_is_the_options_else_the_files_else_the_services_default(tmp_path):
    # the calibrator answers its status on a session of its own only as a client (behind a router)
    own = tmp_path / "z.json5"
    own.write_text('{ mode: "client" }')
    assert session_mode(ZenohSettings(config=str(own))) == "client"
    assert session_mode(ZenohSettings(config=str(own), mode="peer")) == "peer"
    assert session_mode(ZenohSettings()) == "peer"
    assert session_mode(ZenohSettings(mode="client", connect=("tcp/127.0.0.1:7447",))) == "client"
