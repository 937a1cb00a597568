-- Run once on the primary (db-1) as postgres: psql -v ON_ERROR_STOP=1 -f setup.sql
-- The calibrators' role owns the database; the first calibrator to start makes the two tables (the same schema as
-- the SQLite file: calibrations, changes; a UNIQUE index on (device, version)).
CREATE ROLE magnet LOGIN PASSWORD :'magnet_password';
CREATE DATABASE magnet OWNER magnet ENCODING 'UTF8' TEMPLATE template0;
-- streaming replication to the standby, through a slot so the primary keeps WAL the standby has not received
CREATE ROLE replicator LOGIN REPLICATION PASSWORD :'replicator_password';
SELECT pg_create_physical_replication_slot('magnet_standby');
