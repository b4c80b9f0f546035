"""Tools around the live system: `keo bench`, its transport-floor relay, `keo demo` and the
process management they share."""
