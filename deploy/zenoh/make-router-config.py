#!/usr/bin/env python3
"""Writes the Zenoh router configuration for a stillmap fleet: TLS with client
certificates (mTLS) on the router's listen endpoint, and an access-control list
that denies everything by default and lets

  * the stillmap server (certificate common name --server-cn) publish and
    subscribe on stillmap/** (and announce itself on stillmap-cluster/**, which
    servers and tools with its certificate read), and
  * each robot, whose certificate's common name is its robot id, publish and
    subscribe only on stillmap/<robot>/** (its frames key, its results key),

so a robot cannot publish frames or hellos for another robot, nor read another
robot's results. Zenoh reads the ACL once: after adding a robot, run this again
and restart the router (zenohd -c router.json5).

  deploy/zenoh/make-router-config.py --robots robot-a,robot-b \\
      --ca ca.pem --cert router.pem --key router.key > router.json5
"""
import argparse
import json
import re
import sys

# stillmap's robot ids (proto/src/lib.rs validate_robot_id): one key segment.
ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
# Every message kind Zenoh 1.x's ACL knows.
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]
ROBOT_MESSAGES = ["put", "declare_subscriber", "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]


def router_config(robots, server_cn, listen, ca, cert, key):
    rules = [{"id": "server", "permission": "allow", "flows": ["ingress", "egress"],
              "messages": ALL_MESSAGES, "key_exprs": ["stillmap/**", "stillmap-cluster/**"]}]
    subjects = [{"id": "server", "cert_common_names": [server_cn]}]
    policies = [{"id": "server", "rules": ["server"], "subjects": ["server"]}]
    # The server subscribes to every robot's frames with one wildcard: each robot
    # must hear of that subscription (egress) or its publisher sees no subscriber.
    rules.append({"id": "robots hear the server's subscription", "permission": "allow", "flows": ["egress"],
                  "messages": ["declare_subscriber"], "key_exprs": ["stillmap/*/frames"]})
    # Robots follow which servers are live (a server leaving moves its robots): they
    # may subscribe to the servers' liveliness tokens and hear them, never declare one.
    rules.append({"id": "robots follow the live servers", "permission": "allow", "flows": ["ingress"],
                  "messages": ["declare_liveliness_subscriber", "liveliness_query"],
                  "key_exprs": ["stillmap-cluster/servers/*"]})
    rules.append({"id": "robots hear the live servers", "permission": "allow", "flows": ["egress"],
                  "messages": ["liveliness_token", "reply"], "key_exprs": ["stillmap-cluster/servers/*"]})
    for robot in robots:
        rules.append({"id": f"robot {robot}", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": ROBOT_MESSAGES, "key_exprs": [f"stillmap/{robot}/**"]})
        subjects.append({"id": f"robot {robot}", "cert_common_names": [robot]})
        policies.append({"id": f"robot {robot}",
                         "rules": [f"robot {robot}", "robots hear the server's subscription",
                                   "robots follow the live servers", "robots hear the live servers"],
                         "subjects": [f"robot {robot}"]})
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": {
            "root_ca_certificate": ca,
            "listen_certificate": cert,
            "listen_private_key": key,
            "enable_mtls": True,
        }}},
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        },
    }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", required=True, help="comma-separated robot ids (each robot's certificate CN)")
    p.add_argument("--server-cn", default="stillmap-server", help="CN of the stillmap server's client certificate")
    p.add_argument("--listen", default="tls/0.0.0.0:7447", help="the router's listen endpoint")
    p.add_argument("--ca", default="/etc/stillmap/zenoh/ca.pem", help="CA that signed every certificate (PEM)")
    p.add_argument("--cert", default="/etc/stillmap/zenoh/router.pem", help="the router's certificate (PEM)")
    p.add_argument("--key", default="/etc/stillmap/zenoh/router.key", help="the router's private key (PEM)")
    a = p.parse_args()
    robots = [r for r in a.robots.split(",") if r]
    bad = [r for r in robots if not ROBOT_ID.match(r)]
    if bad or not robots:
        print(f"make-router-config: robot ids must be 1-64 of A-Z a-z 0-9 _ -, got {bad or 'none'}", file=sys.stderr)
        sys.exit(2)
    if a.server_cn in robots:
        print(f"make-router-config: {a.server_cn!r} is both the server's CN and a robot id", file=sys.stderr)
        sys.exit(2)
    json.dump(router_config(robots, a.server_cn, a.listen, a.ca, a.cert, a.key), sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
