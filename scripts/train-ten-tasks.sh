#!/usr/bin/env bash
# The ten-task checkpoint (models/policy/pretrained/ten-tasks, see its model card): all ten
# Table-A tasks, 100 demonstrations each, models/policy/ten-tasks.toml (cpu.toml with a
# workspace box that holds the new tasks; about 55 min of training on a 2-core machine).
# See scripts/train-tasks.sh.
exec "$(dirname "${BASH_SOURCE[0]}")/train-tasks.sh" ten-tasks models/policy/ten-tasks.toml \
  open_drawer push_buttons slide_block close_jar stack_blocks \
  meat_off_grill turn_tap put_item_in_drawer drag_stick sweep_to_dustpan
