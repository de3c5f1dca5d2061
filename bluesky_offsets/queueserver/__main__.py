"""``python -m bluesky_offsets.queueserver existing|permissions``: the paths the RE Manager needs."""

import sys

from . import EXISTING_PLANS_AND_DEVICES, USER_GROUP_PERMISSIONS

WHAT = {"existing": EXISTING_PLANS_AND_DEVICES, "permissions": USER_GROUP_PERMISSIONS}

if len(sys.argv) != 2 or sys.argv[1] not in WHAT:
    sys.exit("usage: python -m bluesky_offsets.queueserver existing|permissions")
print(WHAT[sys.argv[1]])
