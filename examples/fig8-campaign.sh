#!/bin/sh
# Figure 8 in profile thesis as a campaign (docs/reproduce.md, 'A campaign over many
# stops'): the sparse arms and their control, then the dense arms once every sparse run
# is complete. The same command again resumes every run from its last cut, so restart it
# after every stop. Run it from a pinned checkout with its own environment so that a
# change on main never alters a run midway:
#
#   git worktree add --detach runs/fig8/src main && (cd runs/fig8/src && make setup)
#   nohup nice -n 19 examples/fig8-campaign.sh > runs/fig8/campaign.log 2>&1 &
#
# MACB_CAMPAIGN_SRC: the pinned checkout (default runs/fig8/src);
# MACB_CAMPAIGN_OUT: the runs and their page (default runs/fig8/out).
set -u
SRC=${MACB_CAMPAIGN_SRC:-runs/fig8/src}
OUT=${MACB_CAMPAIGN_OUT:-runs/fig8/out}
MACB="$SRC/.venv/bin/macb"
[ -x "$MACB" ] || { echo "no $MACB: set up the pinned checkout first (see the head of $0)"; exit 2; }
"$MACB" reproduce fig8 --local --profile thesis --arms 'Sparse*' --out "$OUT" || exit $?
exec "$MACB" reproduce fig8 --local --profile thesis --arms 'Distance*' --out "$OUT"
