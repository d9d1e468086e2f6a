"""Bytes ⇄ typed SI values: frame and event schemas, Zenoh and MAVLink adapters, log and session readers."""
