"""A zenoh plugin's table and its zenoh config file: keys set in the table go over the file, so a
key set in both must agree; keys left out keep the file's value.

Found by review: the example ``config.toml`` sets ``mode = "peer"`` and ``multicast_scouting =
true`` in ``[transports.zenoh]``. Uncommenting its ``config_file`` line for ``robot-tls.json5`` (a
TLS client that does not scout) gave a peer that scouted and listened on plain TCP, and
``check-config`` said ok. And the ``ros2`` output and source set their table's defaults (a peer
without scouting) over every file, named in the table or not.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapd.outputs.ros2_options import Ros2OutputOptions
from mapd.ros2.cdr import session_config, session_options_for
from transports.zenoh.session import ZenohOptions, build_config

REPO = Path(__file__).resolve().parents[3]
CLIENT = (
    '{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7447"]}, scouting: {multicast: {enabled: false}}}'
)


def _get(conf: object, key: str) -> object:
    return json.loads(conf.get_json(key))  # type: ignore[attr-defined]


def test_the_example_tables_keys_over_the_tls_client_file_are_refused_with_one_line() -> None:
    opts = ZenohOptions(
        mode="peer", multicast_scouting=True, config_file=REPO / "deploy/zenoh/robot-tls.json5"
    )
    with pytest.raises(ValueError) as err:
        opts.check_files()
    line = str(err.value)
    assert line.startswith("config_file: ") and "\n" not in line, line
    assert 'mode "peer" here, "client" there; multicast_scouting true here, false there' in line, line
    assert line.endswith(
        "a key set in both must agree (set here, it goes over the file); leave it out of one"
    )


def test_keys_that_agree_or_that_the_file_leaves_out_are_taken(tmp_path: Path) -> None:
    client = tmp_path / "client.json5"
    client.write_text(CLIENT)
    ZenohOptions(mode="client", multicast_scouting=False, config_file=client).check_files()  # agree
    only_tls = tmp_path / "tls-only.json5"  # mode, endpoints and scouting left to the table
    only_tls.write_text("{transport: {link: {tx: {lease: 12000}}}}")
    opts = ZenohOptions(
        mode="client", connect=["tcp/127.0.0.1:7447"], multicast_scouting=False, config_file=only_tls
    )
    opts.check_files()
    conf = build_config(opts, 1 << 20)
    assert _get(conf, "mode") == "client" and _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    # the table left out: the file's values stand
    conf = build_config(ZenohOptions(config_file=client), 1 << 20)
    assert _get(conf, "mode") == "client" and _get(conf, "scouting/multicast/enabled") is False


def test_the_ros2_output_keeps_the_files_mode_and_endpoints_unless_its_table_sets_them(
    tmp_path: Path,
) -> None:
    client = tmp_path / "client.json5"
    client.write_text(CLIENT.replace("tcp/127.0.0.1:7447", "tcp/10.0.0.5:7447"))
    conf = session_config(**session_options_for(Ros2OutputOptions(zenoh_config=client)))
    assert _get(conf, "mode") == "client" and _get(conf, "connect/endpoints") == ["tcp/10.0.0.5:7447"]
    assert _get(conf, "scouting/multicast/enabled") is False
    # without a file, the table's defaults: a peer that does not scout
    conf = session_config(**session_options_for(Ros2OutputOptions()))
    assert _get(conf, "mode") == "peer" and _get(conf, "scouting/multicast/enabled") is False
    with pytest.raises(
        ValueError, match=r'^zenoh_config: .*: mode "peer" here, "client" there: a key set in both'
    ):
        Ros2OutputOptions(mode="peer", zenoh_config=client).check_files()


def test_a_file_that_leaves_the_session_keys_out_keeps_the_ros2_tables_defaults(tmp_path: Path) -> None:
    # A file of TLS or timeouts alone: the source's table defaults (a client of rmw_zenohd on
    # localhost that does not scout) were dropped with the earlier fix, for zenoh's (a peer that
    # scouts the LAN, connected to nothing): found by review.
    from mapd.sources.ros2_options import Ros2Options

    only = tmp_path / "timeouts.json5"
    only.write_text("{transport: {link: {tx: {lease: 12000}}}}")
    conf = session_config(**session_options_for(Ros2Options(zenoh_config=only)))
    assert _get(conf, "mode") == "client" and _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "scouting/multicast/enabled") is False
    assert _get(conf, "transport/link/tx/lease") == 12000
