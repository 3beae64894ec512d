"""What every room's routes share: request dependencies (dependencies), RFC 9457 problem answers and the body and
header guards (problems), strict wire types (schemas), one-pass JSON bodies (json_body), strict query strings
(query_params) and the URLs answers link to (links)."""
