"""What the vehicles and the service share: the wire protocol (:mod:`agv_protocol.wire`: key expressions and
encodings, specified in docs/protocol.md). Both sides import this package; it imports neither of them."""
