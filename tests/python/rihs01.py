#!/usr/bin/env python3
"""REP-2016 type hashes (RIHS01) of ROS 2 messages from their .msg files, standard library only.

An implementation independent of minflow's Rust one (src/msgs/type_hash.rs), written from
ROS 2 Jazzy's rosidl: rosidl_adapter's .msg -> IDL mapping (char -> uint8, byte -> octet),
rosidl_generator_type_description's serialize_field_type / extract_full_type_description /
calculate_type_hash (the description as a dict, default values dropped, referenced types
sorted by name, hashed as json.dumps(..., ensure_ascii=True, separators=(', ', ': '))).

Usage: rihs01.py [--msg-dir MSG_DIR] [--def pkg/msg/Type=FILE]... [--json] TYPE...
TYPE is pkg/msg/Type. MSG_DIR (default msgs) holds pkg/Type.msg, or Type.msg for minflow's
own package (minflow's msgs/ layout); --def pkg/msg/Type=FILE gives a file explicitly. Prints one JSON object {type: hash} on
stdout; --json adds each hashed text under "TYPE json".
"""

import argparse
import hashlib
import json
import os
import re
import sys

# type_description_interfaces/msg/FieldType ids of the value types.
VALUE_TYPE_IDS = {
    'nested': 1, 'int8': 2, 'uint8': 3, 'int16': 4, 'uint16': 5, 'int32': 6, 'uint32': 7,
    'int64': 8, 'uint64': 9, 'float': 10, 'double': 11, 'long double': 12, 'char': 13,
    'wchar': 14, 'boolean': 15, 'octet': 16, 'string': 17, 'wstring': 18,
    'bounded_string': 21, 'bounded_wstring': 22,
}
# FIELD_TYPE_*_ARRAY / _BOUNDED_SEQUENCE / _UNBOUNDED_SEQUENCE = value id + these.
CONTAINER_OFFSETS = {None: 0, 'array': 48, 'bounded_sequence': 96, 'unbounded_sequence': 144}
# rosidl_adapter's .msg primitive -> IDL type.
MSG_TO_IDL = {
    'bool': 'boolean', 'byte': 'octet', 'char': 'uint8', 'float32': 'float',
    'float64': 'double', 'int8': 'int8', 'uint8': 'uint8', 'int16': 'int16',
    'uint16': 'uint16', 'int32': 'int32', 'uint32': 'uint32', 'int64': 'int64',
    'uint64': 'uint64', 'string': 'string', 'wstring': 'wstring',
}
TYPE_RE = re.compile(r'^(?P<base>[^\[\]]+)(\[(?P<bound>[^\]]*)\])?$')


def field_type(type_string, package):
    """The FieldType dict of a .msg type string."""
    m = TYPE_RE.match(type_string)
    if not m:
        raise ValueError(f'bad type {type_string!r}')
    base, bound = m.group('base'), m.group('bound')
    container, capacity = None, 0
    if bound is not None:
        if bound == '':
            container = 'unbounded_sequence'
        elif bound.startswith('<='):
            container, capacity = 'bounded_sequence', int(bound[2:])
        else:
            container, capacity = 'array', int(bound)
    string_capacity, nested = 0, ''
    if base in MSG_TO_IDL:
        value = MSG_TO_IDL[base]
    elif base.startswith('string<=') or base.startswith('wstring<='):
        kind, limit = base.split('<=')
        value, string_capacity = 'bounded_' + kind, int(limit)
    else:
        pkg, _, name = base.rpartition('/')
        nested = f'{pkg or package}/msg/{name}'
        value = 'nested'
    return {
        'type_id': VALUE_TYPE_IDS[value] + CONTAINER_OFFSETS[container],
        'capacity': capacity,
        'string_capacity': string_capacity,
        'nested_type_name': nested,
    }


def individual_description(type_name, text):
    """The IndividualTypeDescription dict of one .msg (with default_value, as rosidl keeps it)."""
    package = type_name.split('/')[0]
    fields = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        type_string, rest = line.split(None, 1)
        if '=' in rest:
            continue  # a constant
        parts = rest.split(None, 1)
        fields.append({
            'name': parts[0],
            'type': field_type(type_string, package),
            'default_value': parts[1] if len(parts) > 1 else '',
        })
    if not fields:
        fields.append({'name': 'structure_needs_at_least_one_member',
                       'type': field_type('uint8', package), 'default_value': ''})
    return {'type_name': type_name, 'fields': fields}


def full_description(type_name, load):
    """The TypeDescription dict: the type and everything it references, sorted by name."""
    top = individual_description(type_name, load(type_name))
    found = {}
    queue = [f['type']['nested_type_name'] for f in top['fields'] if f['type']['nested_type_name']]
    while queue:
        name = queue.pop()
        if name in found:
            continue
        found[name] = individual_description(name, load(name))
        queue.extend(f['type']['nested_type_name'] for f in found[name]['fields']
                     if f['type']['nested_type_name'])
    return {
        'type_description': top,
        'referenced_type_descriptions': [found[n] for n in sorted(found)],
    }


def hashed_text(description):
    """What rosidl's calculate_type_hash feeds to SHA-256."""
    d = json.loads(json.dumps(description))
    for td in [d['type_description']] + d['referenced_type_descriptions']:
        for f in td['fields']:
            del f['default_value']
    return json.dumps(d, skipkeys=False, ensure_ascii=True, check_circular=True,
                      allow_nan=False, indent=None, separators=(', ', ': '), sort_keys=False)


def rihs01(description):
    return 'RIHS01_' + hashlib.sha256(hashed_text(description).encode('utf-8')).hexdigest()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('types', nargs='+', metavar='TYPE')
    parser.add_argument('--msg-dir', default='msgs')
    parser.add_argument('--def', dest='defs', action='append', default=[],
                        help='pkg/msg/Type=FILE')
    parser.add_argument('--json', action='store_true')
    args = parser.parse_intermixed_args()
    explicit = dict(d.split('=', 1) for d in args.defs)

    def load(type_name):
        if type_name in explicit:
            path = explicit[type_name]
        else:
            pkg, _, name = type_name.split('/')
            path = os.path.join(args.msg_dir, pkg, name + '.msg')
            if not os.path.exists(path):
                path = os.path.join(args.msg_dir, name + '.msg')
        with open(path, encoding='utf-8') as f:
            return f.read()

    out = {}
    for t in args.types:
        description = full_description(t, load)
        out[t] = rihs01(description)
        if args.json:
            out[t + ' json'] = hashed_text(description)
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == '__main__':
    main()
