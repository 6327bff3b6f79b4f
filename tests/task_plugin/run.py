"""The CLI with the toy task declared first (one `Task` entry), as a plug-in of a user would declare it."""
import sys

from pairedgta import tasks

tasks.TASKS["presence"] = tasks.Task(
    "presence", "segmenter",
    {"pseudolabel": "presence_task:PresencePseudolabels", "evaluate": "presence_task:PresenceEvaluate"},
    what="class presence", title="mean presence recall", example="model=tiny_segformer")

from pairedgta.__main__ import cli  # noqa: E402

sys.argv = ["pairedgta", *sys.argv[1:]]
cli()
