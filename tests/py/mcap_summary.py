#!/usr/bin/env python3
"""Summarises an MCAP file with the `mcap` Python package (the MCAP test's second,
independent reader; `make deps` installs it): per channel the schema, encodings,
message count, first/last log time and whether log times increase; the metadata
records. Prints JSON. Usage: mcap_summary.py FILE.mcap"""
import json
import sys

from mcap.reader import make_reader


def main(path):
    channels = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        last_any = None
        increasing_overall = True
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            c = channels.setdefault(channel.topic, {
                "schema": schema.name if schema else None,
                "schema_encoding": schema.encoding if schema else None,
                "message_encoding": channel.message_encoding,
                "count": 0,
                "first_log_time": message.log_time,
                "last_log_time": None,
                "increasing": True,
            })
            if c["last_log_time"] is not None and message.log_time < c["last_log_time"]:
                c["increasing"] = False
            if last_any is not None and message.log_time < last_any:
                increasing_overall = False
            last_any = message.log_time
            c["last_log_time"] = message.log_time
            c["count"] += 1
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    print(json.dumps({"channels": channels, "metadata": metadata,
                      "increasing_in_file_order": increasing_overall}))


if __name__ == "__main__":
    main(sys.argv[1])
