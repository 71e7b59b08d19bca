-- The fleet's PostgreSQL: one login role and one database for all the cells
-- (docs/fleet.md). celld makes its own tables in it when it first connects.
-- Run once as a superuser, with the cells' password:
--   psql -U postgres -v ON_ERROR_STOP=1 -v password='…' -f deploy/fleet/create-fleet-database.sql
-- Then let the cells in (pg_hba.conf, their network), for example:
--   host  fleet  celld  10.20.0.0/16  scram-sha-256
-- and have PostgreSQL listen on that network (postgresql.conf: listen_addresses).
CREATE ROLE celld LOGIN PASSWORD :'password';
CREATE DATABASE fleet OWNER celld;
